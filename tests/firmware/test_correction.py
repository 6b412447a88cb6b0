"""The fixed-point correction through ctypes against magcal.device.fixed_point.

Criteria, on 10^6 random samples (3 * 10^6 outputs) over unit-scale, counts-scale, ~60-scale
and extreme parameter sets, with default and arbitrary output exponents:

- bit-exact equality with fixed_point.emulate (exact integer emulation);
- the requirement: |out - clip(ref)| <= 1 LSB, ref = fixed_point.reference_lsb (float64
  D_inv (y - o) for the stored parameters, unrounded) clipped to the int32 range;
- the design property: |out - ref| <= 1/2 LSB (+ 2^-20) whenever ref is inside the range,
  since the device rounds the exact value once.
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from magcal.device import fixed_point as fp
from magcal.device.generated import Status
from tests.firmware.test_params import McParams, bind_params, to_struct

T30 = 1 << 30
READY = 0x4D43434F  # MC_CORRECTION_READY


class McCorrection(ctypes.Structure):
    """mc_correction_t (correction.h)."""

    _fields_ = [
        ("params", McParams),
        ("ready", ctypes.c_uint32),
        ("shift", ctypes.c_uint8),
    ]


I16P = ctypes.POINTER(ctypes.c_int16)
I32P = ctypes.POINTER(ctypes.c_int32)


@pytest.fixture(scope="module")
def lib(fwlib):
    bind_params(fwlib)
    fwlib.mc_correction_init.restype = ctypes.c_int
    fwlib.mc_correction_init.argtypes = [ctypes.POINTER(McCorrection), ctypes.POINTER(McParams)]
    fwlib.mc_correction_apply.restype = ctypes.c_int
    fwlib.mc_correction_apply.argtypes = [ctypes.POINTER(McCorrection), I16P, I32P]
    fwlib.mc_correction_apply_n.restype = ctypes.c_int
    fwlib.mc_correction_apply_n.argtypes = [
        ctypes.POINTER(McCorrection),
        I16P,
        ctypes.c_size_t,
        I32P,
    ]
    return fwlib


def init(lib, p: fp.DeviceParams) -> McCorrection:
    c = McCorrection()
    assert lib.mc_correction_init(ctypes.byref(c), to_struct(p)) == Status.OK
    assert c.ready == READY and c.shift == p.shift
    return c


def apply_n(lib, c: McCorrection, raw: np.ndarray) -> np.ndarray:
    raw = np.ascontiguousarray(raw, dtype=np.int16)
    out = np.empty(raw.shape, dtype=np.int32)
    st = lib.mc_correction_apply_n(
        ctypes.byref(c), raw.ctypes.data_as(I16P), raw.shape[0], out.ctypes.data_as(I32P)
    )
    assert st == Status.OK
    return out


def apply_one(lib, c: McCorrection, y) -> list[int]:
    raw = (ctypes.c_int16 * 3)(*y)
    out = (ctypes.c_int32 * 3)()
    assert lib.mc_correction_apply(ctypes.byref(c), raw, out) == Status.OK
    return list(out)


def check_against_references(p: fp.DeviceParams, raw: np.ndarray, out: np.ndarray) -> dict:
    """Asserts the three criteria of the module docstring; returns the measured figures."""
    np.testing.assert_array_equal(out, fp.emulate(p, raw))
    ref = fp.reference_lsb(p, raw)
    clipped = np.clip(ref, fp.INT32_MIN, fp.INT32_MAX)
    err_clipped = np.abs(out - clipped)
    assert np.max(err_clipped) <= 1.0
    inside = (ref <= fp.INT32_MAX + 0.5) & (ref >= fp.INT32_MIN - 0.5)
    err = np.abs(out - ref)[inside]
    assert np.all(err <= 0.5 + 2.0**-20)
    return {
        "n": out.size,
        "saturated": int(np.count_nonzero(~inside)),
        "max_err": float(np.max(err, initial=0.0)),
        "max_err_clipped": float(np.max(err_clipped)),
    }


def random_set(rng: np.random.Generator, kind: str, default_out: bool) -> fp.DeviceParams:
    while True:
        if kind == "extreme":
            e_d = int(rng.integers(fp.EXP_MIN, fp.EXP_MAX + 1))
            d = tuple(int(v) for v in rng.integers(-T30, T30 + 1, 9))
            off = tuple(int(v) for v in rng.integers(-T30, T30 + 1, 3))
            e_m = fp.default_out_exp(e_d, d, off)
            p = fp.DeviceParams(e_d, e_m, d, off)
        else:
            scale = {
                "unit": rng.uniform(0.5, 1.5),
                "counts": 1 / (30 * 1000 ** rng.uniform()),  # field of 30..30000 counts
                "sixty": 60 * rng.uniform(0.5, 1.5),
            }[kind]
            m = np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))
            try:
                p = fp.from_calibration(scale * m, rng.uniform(-2000, 2000, 3))
            except fp.FixedPointError:
                continue
        if not default_out:  # any allowed output exponent: shift 0 (saturates) to 62
            lo = max(fp.EXP_MIN, p.d_inv_exp - 14)
            hi = min(fp.EXP_MAX, p.d_inv_exp + 48)
            p = fp.DeviceParams(p.d_inv_exp, int(rng.integers(lo, hi + 1)), p.d_inv, p.offset)
        try:
            fp.validate(p)
        except fp.FixedPointError:
            continue
        return p


def random_raw(rng: np.random.Generator, p: fp.DeviceParams, n: int) -> np.ndarray:
    """Uniform int16, the extremes, and values near the offset (a real field)."""
    raw = rng.integers(-32768, 32768, (n, 3))
    pick = rng.integers(0, 16, (n, 3))
    near = np.clip(np.round(p.offset_counts()) + rng.integers(-1000, 1001, (n, 3)), -32768, 32767)
    raw = np.where(pick < 7, near, raw)
    raw = np.where(pick == 14, -32768, raw)
    raw = np.where(pick == 15, 32767, raw)
    return raw.astype(np.int16)


def test_million_random_cases(lib):
    rng = np.random.default_rng(2024)
    kinds = ["unit", "counts", "sixty", "extreme"]
    n_sets, per_set = 400, 2500  # 10^6 samples, 3 * 10^6 outputs
    totals = {"n": 0, "saturated": 0, "max_err": 0.0, "max_err_clipped": 0.0}
    for k in range(n_sets):
        p = random_set(rng, kinds[k % 4], default_out=(k // 4) % 2 == 0)
        c = init(lib, p)
        raw = random_raw(rng, p, per_set)
        figures = check_against_references(p, raw, apply_n(lib, c, raw))
        totals["n"] += figures["n"]
        totals["saturated"] += figures["saturated"]
        totals["max_err"] = max(totals["max_err"], figures["max_err"])
        totals["max_err_clipped"] = max(totals["max_err_clipped"], figures["max_err_clipped"])
        if k % 50 == 0:  # the single-sample entry point gives the same
            for y, want in zip(raw[:20], apply_n(lib, c, raw[:20]), strict=True):
                assert apply_one(lib, c, y) == list(want)
    print(f"random: {totals}")
    assert totals["n"] >= 3_000_000
    assert 0 < totals["saturated"] < totals["n"] // 2
    assert totals["max_err"] <= 0.5 + 2.0**-20
    assert totals["max_err_clipped"] <= 1.0


def test_default_sets_never_saturate_and_keep_31_bits(lib):
    rng = np.random.default_rng(7)
    for kind in ("unit", "counts", "sixty"):
        p = random_set(rng, kind, default_out=True)
        corners = np.array(
            [[x, y, z] for x in (-32768, 32767) for y in (-32768, 32767) for z in (0, 32767)]
        )
        raw = np.vstack([corners, random_raw(rng, p, 1000)])
        out = apply_n(lib, init(lib, p), raw)
        check_against_references(p, raw, out)
        assert np.all(np.abs(out.astype(np.int64)) < 2**31 - 1)
        assert np.max(np.abs(out.astype(np.int64))) >= 2**29  # the range is used


def test_unit_and_counts_scale_calibrations_end_to_end(lib):
    """A counts-scale calibration (field of 480 counts) gives unit-norm outputs; the same
    calibration in unit scale (D_inv = I, field in counts) gives counts."""
    rng = np.random.default_rng(3)
    a = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    d = 480 * (np.eye(3) + 0.1 * rng.uniform(-1, 1, (3, 3))) @ a  # counts per unit field
    o = np.array([150.0, -820.0, 33.5])
    m_true = rng.normal(size=(5000, 3))
    m_true /= np.linalg.norm(m_true, axis=1, keepdims=True)
    raw = np.round(m_true @ d.T + o).astype(np.int16)

    p = fp.from_calibration(np.linalg.inv(d), o)
    out = apply_n(lib, init(lib, p), raw)
    check_against_references(p, raw, out)
    m = fp.output_to_float(p, out)
    # rounding y to counts moves m by up to ~0.5 sqrt(3) / 400 of the unit field
    assert np.max(np.abs(np.linalg.norm(m, axis=1) - 1)) < 4e-3
    np.testing.assert_allclose(m, np.linalg.solve(d, (raw - o).T).T, atol=1e-6)

    p = fp.from_calibration(np.eye(3), o)
    out = apply_n(lib, init(lib, p), raw)
    check_against_references(p, raw, out)
    np.testing.assert_array_equal(fp.output_to_float(p, out), raw - p.offset_counts())


# rows: all -1, (1, -1, 1), (1, 1, -1): det -4, kappa_inf 3; every |mantissa| = 2^30
SIGNS = (-T30, -T30, -T30, T30, -T30, T30, T30, T30, -T30)


@pytest.mark.parametrize(
    ("e_d", "e_m", "offset", "y", "want"),
    [
        # shift 0: |acc| = 3 2^61 and 2^61 saturate both ways
        (-18, -32, (T30,) * 3, (-32768,) * 3, [fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN]),
        (-18, -32, (-T30,) * 3, (32767,) * 3, [fp.INT32_MIN, fp.INT32_MAX, fp.INT32_MAX]),
        # shift 62: 1.5 -> 2, -0.5 -> 0 (ties toward +inf)
        (-16, 32, (T30,) * 3, (-32768,) * 3, [2, 0, 0]),
        # shift 30: 3 2^31 saturates; -2^31 is representable
        (0, 16, (T30,) * 3, (-32768,) * 3, [fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN]),
        (0, 17, (T30,) * 3, (-32768,) * 3, [fp.INT32_MAX, -(1 << 30), -(1 << 30)]),
    ],
)
def test_extreme_parameters_saturate(lib, e_d, e_m, offset, y, want):
    p = fp.DeviceParams(e_d, e_m, SIGNS, offset)
    c = init(lib, p)
    assert apply_one(lib, c, y) == want
    raw = np.array([y])
    assert fp.emulate(p, raw).tolist() == [want]
    check_against_references(p, raw, apply_n(lib, c, raw))


def test_saturation_is_monotone_over_the_whole_input_range(lib):
    p = fp.DeviceParams(0, 10, (T30, 0, 0, 0, T30, 0, 0, 0, T30), (0, 0, 0))  # +-1024 counts
    y = np.arange(-32768, 32768)
    raw = np.stack([y, -y - 1, np.zeros_like(y)], axis=1).astype(np.int16)
    out = apply_n(lib, init(lib, p), raw)
    check_against_references(p, raw, out)
    assert np.all(np.diff(out[:, 0].astype(np.int64)) >= 0)
    assert np.count_nonzero(out[:, 0] == fp.INT32_MAX) == 32767 - 1024 + 1
    assert np.count_nonzero(out[:, 0] == fp.INT32_MIN) == 32768 - 1024 + 1


def test_python_encoding_decodes_in_c_and_corrects_identically(lib):
    p = fp.from_calibration(np.diag([1 / 61.0, 1 / 59.0, 1 / 60.0]), [12.0, -7.25, 100.0])
    s = McParams()
    blob = fp.encode(p)
    assert lib.mc_params_decode(blob, len(blob), ctypes.byref(s)) == Status.OK
    c = McCorrection()
    assert lib.mc_correction_init(ctypes.byref(c), ctypes.byref(s)) == Status.OK
    raw = random_raw(np.random.default_rng(1), p, 1000)
    np.testing.assert_array_equal(apply_n(lib, c, raw), fp.emulate(p, raw))


def test_errors_and_refusals(lib):
    p = fp.from_calibration(np.eye(3), np.zeros(3))
    c = McCorrection()
    raw = np.zeros((1, 3), dtype=np.int16)
    out = np.zeros((1, 3), dtype=np.int32)
    rp, op = raw.ctypes.data_as(I16P), out.ctypes.data_as(I32P)
    assert lib.mc_correction_apply(ctypes.byref(c), rp, op) == Status.E_STATE
    assert lib.mc_correction_apply_n(ctypes.byref(c), rp, 1, op) == Status.E_STATE
    assert lib.mc_correction_init(None, to_struct(p)) == Status.E_ARG
    assert lib.mc_correction_init(ctypes.byref(c), None) == Status.E_ARG
    c = init(lib, p)
    assert lib.mc_correction_apply(None, rp, op) == Status.E_ARG
    assert lib.mc_correction_apply(ctypes.byref(c), None, op) == Status.E_ARG
    assert lib.mc_correction_apply(ctypes.byref(c), rp, None) == Status.E_ARG
    assert lib.mc_correction_apply_n(ctypes.byref(c), rp, 0, op) == Status.E_ARG

    refusals = {
        Status.E_VERSION: fp.DeviceParams(0, 15, p.d_inv, p.offset, version=3),
        Status.E_EXPONENT: fp.DeviceParams(0, -15, p.d_inv, p.offset),
        Status.E_RANGE: fp.DeviceParams(0, 15, p.d_inv, (0, T30 + 1, 0)),
        Status.E_SINGULAR: fp.DeviceParams(0, 15, (T30, 0, 0, 0, T30, 0, 0, 0, 0), p.offset),
        Status.E_CONDITION: fp.DeviceParams(
            0, 15, (T30, 0, 0, 0, T30, 0, 0, 0, T30 // 101), p.offset
        ),
    }
    assert len(set(refusals)) == 5
    for status, bad in refusals.items():
        c = init(lib, p)
        assert lib.mc_correction_init(ctypes.byref(c), to_struct(bad)) == status
        assert c.ready != READY
        assert lib.mc_correction_apply(ctypes.byref(c), rp, op) == Status.E_STATE
        with pytest.raises(fp.FixedPointError) as err:
            fp.validate(bad)
        assert err.value.status == status
