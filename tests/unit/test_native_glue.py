# SPDX-License-Identifier: Apache-2.0
"""The CPython glue of the native kernel (host/csrc/_mekf_module.c): argument checking.

Every buffer must be C-contiguous float64 of the right length, outputs writable; anything
else is an error that names the argument, never a silently wrong result."""

import ctypes

import numpy as np
import pytest

from magcal.calib.likelihood import _mekf, mekf
from tests.synthetic import synthetic_filter_problem

N = 50

# Positions in the argument tuple of _mekf.cost / _mekf.cost_grad.
MODEL, DT, GYR, ACC, MAG, EXTRA, G, Q0, P0, USE_MAG = range(10)


@pytest.fixture(scope="module")
def problem():
    p, data, _ = synthetic_filter_problem(n=N, inflation="mixed")
    return p, data, (mekf._model_buffer(p), *mekf._data_args(data), True)


def with_arg(args, index, value):
    args = list(args)
    args[index] = value
    return tuple(args)


def cost(args, q=None, innov=None, normalised=None):
    return _mekf.cost(*args, q, innov, normalised)


def cost_grad(args, tape=None, grad=None):
    tape = mekf.new_tape(N) if tape is None else tape
    grad = np.empty(mekf.MODEL_DOUBLES) if grad is None else grad
    return _mekf.cost_grad(*args, tape, grad)


def test_valid_arguments_give_the_cost(problem):
    p, data, args = problem
    c = cost(args)
    assert np.isfinite(c)
    assert cost_grad(args) == pytest.approx(c, rel=1e-14)
    assert mekf.MODEL_DOUBLES == 46


@pytest.mark.parametrize(
    ("index", "dtype", "fmt"),
    [(DT, np.int64, "'[lq]'"), (ACC, np.float32, "'f'"), (MODEL, np.int32, "'[il]'")],
)
def test_input_of_another_dtype_is_an_error(problem, index, dtype, fmt):
    _, _, args = problem
    name = {DT: "dt", ACC: "acc", MODEL: "model"}[index]
    bad = with_arg(args, index, np.asarray(args[index]).astype(dtype))
    for call in (cost, cost_grad):
        with pytest.raises(
            TypeError, match=rf"{name}: expected float64 values, got buffer format {fmt}"
        ):
            call(bad)


def test_input_of_foreign_byte_order_is_an_error(problem):
    _, _, args = problem
    swapped = args[GYR].astype(args[GYR].dtype.newbyteorder())
    with pytest.raises(TypeError, match="gyr: expected float64 values"):
        cost(with_arg(args, GYR, swapped))


def test_explicit_native_order_float64_is_accepted(problem):
    """ctypes exports c_double arrays with format "<d" (explicit little-endian)."""
    _, _, args = problem
    if np.dtype(float).byteorder == ">" or not np.little_endian:  # pragma: no cover
        pytest.skip("big-endian host")
    dt = (ctypes.c_double * N)(*args[DT])
    assert memoryview(dt).format == "<d"
    assert cost(with_arg(args, DT, dt)) == cost(args)


def test_input_of_wrong_length_reports_values_on_both_sides(problem):
    _, _, args = problem
    short = np.ascontiguousarray(args[ACC].ravel()[:-3])
    with pytest.raises(ValueError, match=rf"acc: expected {3 * N} float64 values, got {3 * N - 3}"):
        cost(with_arg(args, ACC, short))
    with pytest.raises(ValueError, match=r"model: expected 46 float64 values, got 45"):
        cost_grad(with_arg(args, MODEL, args[MODEL][:-1].copy()))
    with pytest.raises(ValueError, match=rf"acc_extra_var: expected {N} float64 values"):
        cost(with_arg(args, EXTRA, np.zeros(N + 1)))


def test_non_contiguous_input_is_an_error(problem):
    _, _, args = problem
    strided = np.repeat(args[GYR], 2, axis=0)[::2]
    with pytest.raises(ValueError, match="gyr: .*contiguous"):
        cost(with_arg(args, GYR, strided))


def test_no_samples_is_an_error(problem):
    _, _, args = problem
    empty = with_arg(args, DT, np.empty(0))
    for call in (cost, cost_grad):
        with pytest.raises(ValueError, match="dt: no samples"):
            call(empty)


def test_acc_extra_var_none_means_no_inflation(problem):
    _, _, args = problem
    assert cost(with_arg(args, EXTRA, None)) == cost(with_arg(args, EXTRA, np.zeros(N)))


def test_masks_are_bool_or_uint8_of_the_right_length(problem):
    _, _, args = problem
    mask = np.arange(N) % 3 > 0
    c = cost(args, None, None, None)
    assert _mekf.cost(*args, None, None, None, mask, None) != c
    assert _mekf.cost(*args, None, None, None, mask.astype(np.uint8), None) == _mekf.cost(
        *args, None, None, None, mask, None
    )
    tape, grad = mekf.new_tape(N), np.empty(mekf.MODEL_DOUBLES)
    assert _mekf.cost_grad(*args, tape, grad, None, mask) == pytest.approx(
        _mekf.cost(*args, None, None, None, None, mask), rel=1e-14
    )
    with pytest.raises(TypeError, match="has_acc: expected bool or uint8 values, got .*'d'"):
        _mekf.cost(*args, None, None, None, mask.astype(float), None)
    with pytest.raises(TypeError, match="has_mag: expected bool or uint8 values"):
        _mekf.cost_grad(*args, tape, grad, None, mask.astype(np.int32))
    with pytest.raises(ValueError, match=rf"has_mag: expected {N} values, got {N - 1}"):
        _mekf.cost(*args, None, None, None, None, mask[:-1].copy())
    with pytest.raises(ValueError, match="has_acc: .*contiguous"):
        _mekf.cost(*args, None, None, None, np.repeat(mask, 2)[::2], None)


def test_outputs_must_be_writable_float64_of_the_right_length(problem):
    _, _, args = problem
    read_only = np.empty((N, 4))
    read_only.flags.writeable = False
    with pytest.raises(ValueError, match="q_filt: .*read-only"):
        cost(args, q=read_only)
    with pytest.raises(TypeError, match="innov: expected float64 values, got buffer format 'f'"):
        cost(args, innov=np.empty((N, 6), dtype=np.float32))
    with pytest.raises(
        ValueError, match=rf"normalised: expected {6 * N} float64 values, got {6 * N - 6}"
    ):
        cost(args, normalised=np.empty((N - 1, 6)))
    with pytest.raises(BufferError, match="q_filt: .*not writable"):
        cost(args, q=bytes(8 * 4 * N))  # a read-only buffer of the right size


def test_tape_and_gradient_buffers_are_checked(problem):
    _, _, args = problem
    n_tape = mekf.TAPE_DOUBLES_PER_SAMPLE * N
    with pytest.raises(
        ValueError, match=rf"tape: expected {n_tape} float64 values, got {n_tape - 1}"
    ):
        cost_grad(args, tape=np.empty(n_tape - 1))
    with pytest.raises(TypeError, match="tape: expected float64 values, got buffer format 'f'"):
        cost_grad(args, tape=np.empty(n_tape, dtype=np.float32))
    read_only = np.empty(n_tape)
    read_only.flags.writeable = False
    with pytest.raises(ValueError, match="tape: .*read-only"):
        cost_grad(args, tape=read_only)
    with pytest.raises(TypeError, match="grad: expected float64 values, got buffer format 'f'"):
        cost_grad(args, grad=np.empty(mekf.MODEL_DOUBLES, dtype=np.float32))
    with pytest.raises(ValueError, match=r"grad: expected 46 float64 values, got 47"):
        cost_grad(args, grad=np.empty(mekf.MODEL_DOUBLES + 1))


def test_failed_cost_leaves_a_zero_gradient(problem):
    _, _, args = problem
    model = args[MODEL].copy()
    model[-9:] = -np.eye(3).ravel()  # Σm not positive definite
    grad = np.full(mekf.MODEL_DOUBLES, 7.0)
    assert np.isnan(cost_grad(with_arg(args, MODEL, model), grad=grad))
    assert np.all(grad == 0.0)


def test_wrapper_checks_the_tape(problem):
    p, data, _ = problem
    n_tape = mekf.TAPE_DOUBLES_PER_SAMPLE * N
    c, _ = mekf.cost_and_model_gradient(p, data, mekf.new_tape(N))
    assert np.isfinite(c)
    with pytest.raises(
        ValueError, match=rf"tape: expected shape \({n_tape},\).*got \({n_tape + 1},\)"
    ):
        mekf.cost_and_model_gradient(p, data, np.empty(n_tape + 1))
    with pytest.raises(TypeError, match="tape: expected a float64 array .* got dtype float32"):
        mekf.cost_and_model_gradient(p, data, np.empty(n_tape, dtype=np.float32))
    with pytest.raises(TypeError, match="tape: expected a float64 array .* got list"):
        mekf.cost_and_model_gradient(p, data, [0.0] * n_tape)
