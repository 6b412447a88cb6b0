# SPDX-License-Identifier: Apache-2.0
"""The fixed-point correction through ctypes against magcal.device.fixed_point.

Criteria, on 10^6 random samples (3 * 10^6 outputs) over unit-scale, counts-scale, ~60-scale
and extreme parameter sets, with default and arbitrary output exponents:

- bit-exact equality with fixed_point.emulate (exact integer emulation);
- |out - clip(ref)| <= 1 LSB, ref = fixed_point.reference_lsb (float64 D_inv (y - o) for the
  stored parameters, unrounded) clipped to the int32 range;
- the design property: |out - ref| <= 1/2 LSB (+ 2^-20) whenever ref is inside the range,
  since the device rounds the exact value once.

And the product requirement, on about 10^6 more samples (random, near the offset and every
int16 corner) over random calibrations given as floats (unit-scale, counts-scale with a field
of 3400 counts and offsets of thousands of counts, any field of 30..30000 counts, ~60-scale, a
session in uT, extreme matrices and offsets) converted with the default output exponent: the
device never saturates and |out - D_inv (y - o)| <= 1 LSB, unrounded, with the UNQUANTISED
D_inv and o (both an accurate evaluation and a plain float64 one).
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


def test_default_sets_never_saturate_and_use_the_range(lib):
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
        # The range is used, less the steps the quantisation bound costs (fixed_point.
        # default_out_exp) over the exponent that only avoids saturation.
        steps = p.out_exp - fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset)
        assert 0 <= steps <= 3
        assert np.max(np.abs(out.astype(np.int64))) >= 2 ** (29 - steps)


# ----------------------------------------- the requirement: against the unquantised float

CORNERS = np.array(
    [[x, y, z] for x in (-32768, 32767) for y in (-32768, 32767) for z in (-32768, 32767)]
)


def float_error_lsb(
    p: fp.DeviceParams, d: np.ndarray, o: np.ndarray, raw: np.ndarray, out: np.ndarray
) -> np.ndarray:
    """out - D (y - o) in output LSBs, D (3, 3) and o (3,) the UNQUANTISED calibration in raw
    counts, unrounded, evaluated accurately for unsaturated outputs: out minus the exact
    D_q (y - o_q) from the integers (acc = hi 2^s + lo, 0 <= lo < 2^s), plus the quantisation
    part dD (y - o_q) + D (o - o_q) (dD = D_q - D), a small quantity that float64 gets to
    about 2^-50 LSB."""
    y = raw.astype(np.int64)
    diff = y * 32768 - np.array(p.offset, dtype=np.int64)
    dm = np.array(p.d_inv, dtype=np.int64).reshape(3, 3)
    acc = diff[:, 0:1] * dm[:, 0] + diff[:, 1:2] * dm[:, 1] + diff[:, 2:3] * dm[:, 2]
    s = p.shift
    hi = acc >> s
    lo = acc & ((1 << s) - 1)
    exact_q_minus_out = (hi - out.astype(np.int64)).astype(np.float64) + np.ldexp(
        lo.astype(np.float64), -s
    )
    yq = y.astype(np.float64) - p.offset_counts()  # exact
    quant = yq @ (p.d_inv_matrix() - d).T + (o - p.offset_counts()) @ d.T
    return np.ldexp(quant, 31 - p.out_exp) - exact_q_minus_out


def random_calibration(rng: np.random.Generator, kind: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(D_inv, o, unit_per_count) as a calibration result would give them (floats)."""
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    distortion = (np.eye(3) + 0.15 * rng.uniform(-1, 1, (3, 3))) @ q
    if kind == "unit":  # D_inv about 1: output in counts
        return rng.uniform(0.5, 1.5) * distortion, rng.uniform(-5000, 5000, 3), 1.0
    if kind == "counts3400":  # 50 uT field of 3400 counts, offsets of thousands of counts
        return np.linalg.inv(3400 * distortion), rng.uniform(-6000, 6000, 3), 1.0
    if kind == "counts":  # any field of 30..30000 counts
        field = 30 * 1000 ** rng.uniform()
        return np.linalg.inv(field * distortion), rng.uniform(-1, 1, 3) * (32767 - field), 1.0
    if kind == "sixty":
        return 60 * rng.uniform(0.5, 1.5) * distortion, rng.uniform(-2000, 2000, 3), 1.0
    if kind == "session_uT":  # the session in uT, one count = 50/3400 uT
        upc = 50 / 3400
        return np.linalg.inv(50 * distortion), rng.uniform(-60, 60, 3), upc
    # extreme: entries over 8 decades, any scale that can avoid saturation, offsets anywhere
    # in +-32768 counts or tiny, identity-like or not
    a = rng.uniform(-1, 1, (3, 3)) * 10.0 ** rng.uniform(-8, 0, (3, 3))
    a[np.arange(3), rng.permutation(3)] = rng.choice([-1, 1], 3) * rng.uniform(0.3, 1, 3)
    o = rng.uniform(-32768, 32768, 3) * rng.choice([1.0, 1e-3, 1e-9], 3)
    return a * 2.0 ** rng.uniform(-25, 13), o, 1.0


KINDS = ("unit", "counts3400", "counts", "sixty", "session_uT", "extreme")


def test_output_within_one_lsb_of_the_unquantised_float_correction(lib):
    """|device - float64 D_inv (y - o)| <= 1 LSB unrounded, with the calibration's
    own (unquantised) D_inv and o, for every tested int16 input; and what the default output
    exponent costs over the one that only avoids saturation."""
    rng = np.random.default_rng(55)
    n_sets, per_set = 600, 1700  # about 10^6 samples
    worst = {k: 0.0 for k in KINDS}
    worst_naive = 0.0
    steps: dict[str, dict[int, int]] = {k: {} for k in KINDS}
    lsb_log2: dict[str, list[int]] = {k: [] for k in KINDS}
    n = 0
    k = 0
    while k < n_sets:
        kind = KINDS[k % len(KINDS)]
        d_s, o_s, upc = random_calibration(rng, kind)
        try:
            p = fp.from_calibration(d_s, o_s, unit_per_count=upc)
        except fp.FixedPointError:
            continue  # not representable (conditioning, exponent)
        old = fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset)  # saturation only
        if old == min(fp.EXP_MAX, p.d_inv_exp + 48):
            continue  # saturation is unavoidable (extreme scale): no guarantee to test
        k += 1
        d, o = d_s * upc, o_s / upc  # the same calibration in raw counts
        assert fp.param_error_lsb(p, d_s, o_s, unit_per_count=upc) <= 0.5
        raw = np.vstack([CORNERS, random_raw(rng, p, per_set)]).astype(np.int16)
        out = apply_n(lib, init(lib, p), raw)
        np.testing.assert_array_equal(out, fp.emulate(p, raw))
        assert np.all((out > fp.INT32_MIN) & (out < fp.INT32_MAX))  # never saturated
        err = np.abs(float_error_lsb(p, d, o, raw, out))
        assert np.max(err) <= 1.0, (kind, p, float(np.max(err)))
        # The plain float64 evaluation the host would do, in the session's unit.
        naive = np.ldexp((raw.astype(np.float64) * upc - o_s) @ d_s.T, 31 - p.out_exp)
        err_naive = np.abs(out - naive)
        assert np.max(err_naive) <= 1.0, (kind, p, float(np.max(err_naive)))
        worst[kind] = max(worst[kind], float(np.max(err)))
        worst_naive = max(worst_naive, float(np.max(err_naive)))
        step = p.out_exp - old
        steps[kind][step] = steps[kind].get(step, 0) + 1
        # The proven ceiling (fixed_point.default_out_exp): E_m <= max(old, E_d + 20).
        assert old <= p.out_exp <= max(old, p.d_inv_exp + 20)
        if kind != "extreme":
            assert step <= 3, (kind, p)
        lsb_log2[kind].append(p.out_exp - 31)
        n += out.size
    print(
        f"\n{n} outputs; max |device - unquantised float| (LSB): {worst}, plain float64 "
        f"{worst_naive:.6f}"
    )
    for kind in KINDS:  # one LSB: of the field for counts-scale sets, in counts for unit-scale
        print(
            f"  {kind}: E_m - saturation-only E_m: {dict(sorted(steps[kind].items()))}; "
            f"LSB 2^{np.median(lsb_log2[kind]):.0f} (median)"
        )
    assert n >= 3_000_000
    assert max(worst.values()) > 0.9  # the corners come close to the bound


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
