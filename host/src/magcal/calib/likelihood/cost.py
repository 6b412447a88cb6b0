"""The ML cost V(θ) of eq. (6) and its gradient, exact or by finite differences.

``V(θ) = ½ Σ_t [ ‖y_t − ŷ_t|t−1(θ)‖²_{S_t⁻¹} + log det S_t(θ) ]`` through the MEKF of
``ekf.py``; θ is the 34-vector of ``params.py``.

* :func:`cost_and_gradient` — one forward and one reverse pass of the C kernel: the exact
  gradient for about 2.4 times the price of the cost (``make bench``).
* :func:`numeric_gradient` — the paper's way: finite differences, n_θ + 1 (forward) or
  2 n_θ (central) filter passes.
"""

from __future__ import annotations

import numpy as np

from magcal.calib.likelihood import mekf, params
from magcal.calib.likelihood.mekf import FilterData

# Forward differences have truncation error O(h) and rounding error O(ε|V|/h); h ∝ √ε
# balances them. Central differences: O(h²) against O(ε|V|/h), so h ∝ ∛ε.
_FORWARD_REL_STEP = np.sqrt(np.finfo(float).eps)
_CENTRAL_REL_STEP = np.cbrt(np.finfo(float).eps)


def cost(theta: np.ndarray, data: FilterData) -> float:
    """V(θ) (float, nats). NaN when the filter's covariances break down."""
    return mekf.filter_pass(params.unpack(theta), data, True)


def cost_and_gradient(
    theta: np.ndarray, data: FilterData, tape: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """V(θ) and ∂V/∂θ (34,), exact (reverse mode through the filter)."""
    theta = np.asarray(theta, dtype=float)
    value, mg = mekf.cost_and_model_gradient(params.unpack(theta), data, tape=tape)
    grad = params.model_grad_to_theta(
        theta, mg.D, mg.o, mg.m, mg.gyro_bias, mg.Sigma_gyr, mg.Sigma_acc, mg.Sigma_mag
    )
    return value, grad


def numeric_gradient(
    theta: np.ndarray,
    data: FilterData,
    scheme: str = "forward",
    typical: np.ndarray | None = None,
    value: float | None = None,
) -> np.ndarray:
    """∂V/∂θ by finite differences (34,). ``typical`` (34,) sets each step's scale
    (h_i = rel · max(|θ_i|, typical_i)); ``value`` is V(θ) if already known (forward)."""
    theta = np.asarray(theta, dtype=float)
    scale = np.maximum(np.abs(theta), 1.0 if typical is None else typical)
    grad = np.empty_like(theta)
    if scheme == "forward":
        v0 = cost(theta, data) if value is None else value
        for i in range(theta.size):
            h = _FORWARD_REL_STEP * scale[i]
            e = theta.copy()
            e[i] += h
            grad[i] = (cost(e, data) - v0) / (e[i] - theta[i])
    elif scheme == "central":
        for i in range(theta.size):
            h = _CENTRAL_REL_STEP * scale[i]
            hi, lo = theta.copy(), theta.copy()
            hi[i] += h
            lo[i] -= h
            grad[i] = (cost(hi, data) - cost(lo, data)) / (hi[i] - lo[i])
    else:
        raise ValueError(f"unknown finite-difference scheme {scheme!r}: use 'forward' or 'central'")
    return grad
