# SPDX-License-Identifier: Apache-2.0
"""The device parameter set through ctypes against magcal.device.fixed_point: the encoding
both ways (golden bytes, random sets), the validation verdicts (C and the exact Python mirror
agree on every status), and the host's conversion with its representability errors."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from magcal.device import fixed_point as fp
from magcal.device.generated import Status


class McParams(ctypes.Structure):
    """mc_params_t (params.h): natural alignment, no padding."""

    _fields_ = [
        ("version", ctypes.c_uint16),
        ("d_inv_exp", ctypes.c_int8),
        ("out_exp", ctypes.c_int8),
        ("d_inv", ctypes.c_int32 * 9),
        ("offset", ctypes.c_int32 * 3),
    ]


def to_struct(p: fp.DeviceParams) -> McParams:
    s = McParams()
    s.version = p.version
    s.d_inv_exp = p.d_inv_exp
    s.out_exp = p.out_exp
    s.d_inv[:] = list(p.d_inv)
    s.offset[:] = list(p.offset)
    return s


def from_struct(s: McParams) -> fp.DeviceParams:
    return fp.DeviceParams(
        version=s.version,
        d_inv_exp=s.d_inv_exp,
        out_exp=s.out_exp,
        d_inv=tuple(s.d_inv),
        offset=tuple(s.offset),
    )


def bind_params(lib: ctypes.CDLL) -> ctypes.CDLL:
    lib.mc_params_validate.restype = ctypes.c_int
    lib.mc_params_validate.argtypes = [ctypes.POINTER(McParams)]
    lib.mc_params_encode.restype = ctypes.c_int
    lib.mc_params_encode.argtypes = [
        ctypes.POINTER(McParams),
        ctypes.c_char_p,
        ctypes.c_size_t,
        ctypes.POINTER(ctypes.c_size_t),
    ]
    lib.mc_params_decode.restype = ctypes.c_int
    lib.mc_params_decode.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.POINTER(McParams)]
    return lib


def python_status(p: fp.DeviceParams) -> Status:
    try:
        fp.validate(p)
    except fp.FixedPointError as exc:
        return exc.status
    return Status.OK


@pytest.fixture(scope="module")
def lib(fwlib):
    return bind_params(fwlib)


def c_encode(lib, p: fp.DeviceParams) -> bytes:
    buf = ctypes.create_string_buffer(fp.ENCODED_SIZE)
    written = ctypes.c_size_t(0)
    assert lib.mc_params_encode(to_struct(p), buf, len(buf), ctypes.byref(written)) == Status.OK
    assert written.value == fp.ENCODED_SIZE
    return buf.raw


def c_decode(lib, blob: bytes) -> tuple[int, fp.DeviceParams | None]:
    s = McParams()
    st = lib.mc_params_decode(blob, len(blob), ctypes.byref(s))
    return st, (from_struct(s) if st == Status.OK else None)


GOLDEN = fp.DeviceParams(
    d_inv_exp=-5,
    out_exp=9,
    d_inv=(0x01020304, -0x02040608, 3, -4, 1 << 30, -(1 << 30), 0, 1, -1),
    offset=(-1, 1 << 30, -(1 << 31)),
)
GOLDEN_HEX = (
    "0100fb09" "04030201" "f8f9fbfd" "03000000" "fcffffff" "00000040" "000000c0"
    "00000000" "01000000" "ffffffff" "ffffffff" "00000040" "00000080"
)  # fmt: skip


def test_struct_mirrors_c_layout():
    assert ctypes.sizeof(McParams) == fp.ENCODED_SIZE == 52


def test_golden_bytes_both_sides(lib):
    assert fp.encode(GOLDEN).hex() == GOLDEN_HEX
    assert c_encode(lib, GOLDEN).hex() == GOLDEN_HEX
    assert fp.decode(bytes.fromhex(GOLDEN_HEX)) == GOLDEN
    assert c_decode(lib, bytes.fromhex(GOLDEN_HEX)) == (Status.OK, GOLDEN)


def random_params(rng: np.random.Generator) -> fp.DeviceParams:
    """Any field values the encoding can hold (valid or not)."""
    return fp.DeviceParams(
        d_inv_exp=int(rng.integers(-128, 128)),
        out_exp=int(rng.integers(-128, 128)),
        d_inv=tuple(int(v) for v in rng.integers(-(1 << 31), 1 << 31, 9)),
        offset=tuple(int(v) for v in rng.integers(-(1 << 31), 1 << 31, 3)),
    )


def test_encodings_agree_on_random_sets(lib):
    rng = np.random.default_rng(11)
    for _ in range(2000):
        p = random_params(rng)
        blob = fp.encode(p)
        assert c_encode(lib, p) == blob
        assert c_decode(lib, blob) == (Status.OK, p)
        assert fp.decode(blob) == p


def test_decode_refusals_agree(lib):
    blob = fp.encode(GOLDEN)
    for bad in (blob[:-1], blob + b"\0", b"", b"\x01"):
        assert c_decode(lib, bad)[0] == Status.E_LENGTH
        with pytest.raises(fp.FixedPointError, match=r"has \d+ bytes; format version 1 has 52"):
            fp.decode(bad)
    for version in (0, 2, 0x0101, 0xFFFF):
        bad = version.to_bytes(2, "little") + blob[2:]
        assert c_decode(lib, bad)[0] == Status.E_VERSION
        assert c_decode(lib, bad[:2])[0] == Status.E_VERSION
        with pytest.raises(fp.FixedPointError, match=f"format version {version};") as err:
            fp.decode(bad)
        assert err.value.status == Status.E_VERSION


def test_c_encode_and_decode_argument_errors(lib):
    buf = ctypes.create_string_buffer(fp.ENCODED_SIZE)
    written = ctypes.c_size_t(5)
    s = to_struct(GOLDEN)
    assert lib.mc_params_encode(None, buf, len(buf), ctypes.byref(written)) == Status.E_ARG
    assert lib.mc_params_encode(s, None, len(buf), ctypes.byref(written)) == Status.E_ARG
    assert lib.mc_params_encode(s, buf, len(buf), None) == Status.E_ARG
    assert lib.mc_params_encode(s, buf, 51, ctypes.byref(written)) == Status.E_NO_SPACE
    assert written.value == 0
    assert lib.mc_params_decode(None, 52, ctypes.byref(s)) == Status.E_ARG
    assert lib.mc_params_decode(fp.encode(GOLDEN), 52, None) == Status.E_ARG
    assert lib.mc_params_validate(None) == Status.E_ARG


def random_matrix_params(rng: np.random.Generator) -> fp.DeviceParams:
    """Parameter sets around every refusal: conditioning from 1 to 1e6, exact singularity,
    entries and offsets at and beyond 2^30, exponents and shifts at their limits, versions."""
    a = rng.uniform(-1, 1, (3, 3))
    a[:, rng.integers(3)] *= 10 ** rng.uniform(-6, 0)
    if rng.random() < 0.05:  # exactly dependent rows
        a[2] = a[0] + a[1]
    scale = 2.0 ** rng.integers(8, 31) / np.max(np.abs(a))
    d = np.rint(a * scale).astype(np.int64)
    if rng.random() < 0.05:
        d[2] = d[0] + d[1]  # singular in integers (may also leave the range)
    off = rng.integers(-(1 << 30), (1 << 30) + 1, 3)
    if rng.random() < 0.05:
        d.flat[rng.integers(9)] = rng.choice([(1 << 30) + 1, -(1 << 30) - 1, 1 << 30])
    if rng.random() < 0.05:
        off[rng.integers(3)] = rng.choice([(1 << 30) + 1, -(1 << 30) - 1, -(1 << 30)])
    e_d = int(rng.integers(-34, 35))
    e_m = e_d + int(rng.integers(-16, 50))
    version = 1 if rng.random() < 0.97 else int(rng.integers(0, 65536))
    return fp.DeviceParams(
        d_inv_exp=int(np.clip(e_d, -128, 127)),
        out_exp=int(np.clip(e_m, -128, 127)),
        d_inv=tuple(int(np.clip(v, -(1 << 31), (1 << 31) - 1)) for v in d.ravel()),
        offset=tuple(int(v) for v in off),
        version=version,
    )


def test_validation_verdicts_agree(lib):
    rng = np.random.default_rng(5)
    seen: dict[Status, int] = {}
    for _ in range(5000):
        p = random_matrix_params(rng)
        c_status = Status(lib.mc_params_validate(to_struct(p)))
        assert c_status == python_status(p), p
        seen[c_status] = seen.get(c_status, 0) + 1
    wanted = [Status.OK, Status.E_VERSION, Status.E_EXPONENT, Status.E_RANGE]
    wanted += [Status.E_SINGULAR, Status.E_CONDITION]
    assert all(seen.get(s, 0) >= 50 for s in wanted), seen


def test_condition_agrees_with_numpy():
    rng = np.random.default_rng(8)
    for _ in range(2000):
        p = random_matrix_params(rng)
        a = np.array(p.d_inv, dtype=float).reshape(3, 3)
        kappa = fp.condition_inf(p.d_inv)
        if np.isfinite(kappa) and kappa < 1e8:
            want = np.linalg.norm(a, np.inf) * np.linalg.norm(np.linalg.inv(a), np.inf)
            assert kappa == pytest.approx(want, rel=1e-6)


# ---------------------------------------------------------------- conversion


@pytest.mark.parametrize(
    ("scale", "e_d"),
    [(1.0, 0), (1.3, 1), (1 / 60, -5), (60.0, 6), (1 / 30000, -14), (0.5, -1)],
)
def test_exponent_keeps_full_precision(scale, e_d):
    rng = np.random.default_rng(2)
    m = 0.05 * rng.uniform(-1, 1, (3, 3))
    np.fill_diagonal(m, 1.0)
    d_inv = scale * m  # largest entries exactly `scale`: they set the exponent
    p = fp.from_calibration(d_inv, np.array([12.5, -300.0, 7.0]))
    assert p.d_inv_exp == e_d
    assert max(abs(v) for v in p.d_inv) > 1 << 29  # 30 significant bits
    # quantisation: half a mantissa step
    assert np.max(np.abs(p.d_inv_matrix() - d_inv)) <= 2.0 ** (e_d - 31)
    assert np.max(np.abs(p.offset_counts() - [12.5, -300.0, 7.0])) <= 2.0**-16


def test_unit_per_count_converts_to_counts():
    d_inv = np.diag([0.02, 0.021, 0.019])  # per uT
    o = np.array([3.0, -1.5, 12.0])  # uT
    p = fp.from_calibration(d_inv, o, unit_per_count=0.15)  # 0.15 uT per count
    np.testing.assert_allclose(p.d_inv_matrix(), d_inv * 0.15, rtol=1e-9)
    np.testing.assert_allclose(p.offset_counts(), o / 0.15, atol=2.0**-15)


CORNERS = np.array(
    [[x, y, z] for x in (-32768, 32767) for y in (-32768, 32767) for z in (-32768, 32767)]
)


def corner_error_lsb(p: fp.DeviceParams, d: np.ndarray, o: np.ndarray) -> float:
    """max over the int16 corners of |D_q (y - o_q) - D (y - o)| in p's output LSBs,
    evaluated as dD (y - o_q) + D (o - o_q) in float64 (a small quantity, accurate)."""
    yq = CORNERS - p.offset_counts()
    e = yq @ (p.d_inv_matrix() - d).T + (o - p.offset_counts()) @ d.T
    return float(np.max(np.abs(np.ldexp(e, 31 - p.out_exp))))


def test_default_output_exponent_is_the_smallest_that_never_saturates_and_keeps_1_lsb():
    """E_m is the smallest with (a) no saturation and (b) the parameters' quantisation at
    most half an LSB (less 2^-16) over every int16 input; the bound is exact (attained at a
    corner); one exponent less breaks (a) or (b)."""
    rng = np.random.default_rng(4)
    budget = float(fp.PARAM_ERROR_BUDGET_LSB)
    why = {"saturation": 0, "quantisation": 0}
    for _ in range(300):
        d_inv = (np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))) / 10 ** rng.uniform(-2, 3)
        o = rng.uniform(-3000, 3000, 3)
        p = fp.from_calibration(d_inv, o)
        out = fp.emulate(p, CORNERS).astype(np.int64)
        assert np.all((out > fp.INT32_MIN) & (out < fp.INT32_MAX))
        bound = fp.param_error_lsb(p, d_inv, o)
        assert bound <= budget
        assert corner_error_lsb(p, d_inv, o) == pytest.approx(bound, rel=1e-9, abs=1e-12)
        smaller = fp.DeviceParams(p.d_inv_exp, p.out_exp - 1, p.d_inv, p.offset)
        out = fp.emulate(smaller, CORNERS).astype(np.int64)
        if np.any((out == fp.INT32_MIN) | (out == fp.INT32_MAX)):
            why["saturation"] += 1
        else:
            assert fp.param_error_lsb(smaller, d_inv, o) > budget
            why["quantisation"] += 1
        # Without the unquantised values only (a) counts: the previous rule, never coarser.
        sat_only = fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset)
        assert sat_only <= p.out_exp <= sat_only + 3
    print(why)
    assert why["quantisation"] > 100  # (b) is what sets E_m for most calibrations here


def test_output_exponent_rule_edge_cases():
    # Exactly representable parameters: no quantisation error, the saturation-only exponent.
    o = np.array([150.0, -820.0, 33.5])
    p = fp.from_calibration(np.eye(3), o)
    assert fp.param_error_lsb(p, np.eye(3), o) == 0.0
    assert p.out_exp == fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset) == 16
    # correction.h's examples: I/500 (E_d -8, E_m 7) and 1.1 I (E_d 1, E_m 16), zero offset.
    p = fp.from_calibration(np.eye(3) / 500, np.zeros(3))
    assert (p.d_inv_exp, p.out_exp) == (-8, 7)
    p = fp.from_calibration(1.1 * np.eye(3), np.zeros(3))
    assert (p.d_inv_exp, p.out_exp) == (1, 16)
    # An offset the format cannot hold exactly costs a step here.
    o = np.array([123.4, -2000.7, 300.1])
    p = fp.from_calibration(np.eye(3) / 500, o)
    assert (p.d_inv_exp, p.out_exp) == (-8, 8)
    assert fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset) == 7
    # unit_per_count: the same calibration in uT, its bound taken in the session's unit.
    upc = 0.15
    q = fp.from_calibration(np.eye(3) / 500 / upc, o * upc, unit_per_count=upc)
    assert q.out_exp == 8
    assert 0 < fp.param_error_lsb(q, np.eye(3) / 500 / upc, o * upc, unit_per_count=upc) <= 0.5
    # An explicit out_exp is used as given, even when it gives up the guarantee.
    d_inv = np.array([[1.0, 0.1, -0.2], [0.05, 0.9, 0.3], [0.2, -0.1, 1.1]]) / 3400
    o = np.array([-4321.123, 2345.678, 987.654])
    p = fp.from_calibration(d_inv, o)
    finer = fp.from_calibration(d_inv, o, out_exp=p.out_exp - 2)
    assert finer.out_exp == p.out_exp - 2 and finer.d_inv == p.d_inv
    assert fp.param_error_lsb(finer, d_inv, o) > 0.5
    assert fp.param_error_lsb(p, d_inv, o) <= 0.5
    with pytest.raises(fp.FixedPointError, match="both") as err:
        fp.default_out_exp(p.d_inv_exp, p.d_inv, p.offset, d_inv_exact=d_inv.ravel())
    assert err.value.status == Status.E_ARG


def test_representability_errors_name_the_problem():
    eye = np.eye(3)
    zero = np.zeros(3)
    with pytest.raises(fp.FixedPointError, match="3x3 and o a 3-vector") as err:
        fp.from_calibration(np.eye(2), zero)
    assert err.value.status == Status.E_ARG
    with pytest.raises(fp.FixedPointError, match="non-finite"):
        fp.from_calibration(eye * np.nan, zero)
    with pytest.raises(fp.FixedPointError, match="non-finite"):
        fp.from_calibration(eye, [0.0, np.inf, 0.0])
    with pytest.raises(fp.FixedPointError, match="unit_per_count must be a positive"):
        fp.from_calibration(eye, zero, unit_per_count=0.0)
    with pytest.raises(fp.FixedPointError, match="all zeros") as err:
        fp.from_calibration(0 * eye, zero)
    assert err.value.status == Status.E_SINGULAR
    with pytest.raises(fp.FixedPointError, match=r"exponent -40, outside .*raw counts") as err:
        fp.from_calibration(eye * 2.0**-40, zero)
    assert err.value.status == Status.E_EXPONENT
    with pytest.raises(fp.FixedPointError, match=r"exponent 34, outside") as err:
        fp.from_calibration(eye * 2.0**33.5, zero)
    assert err.value.status == Status.E_EXPONENT
    with pytest.raises(fp.FixedPointError, match=r"o\[1\] = 40000 counts is beyond") as err:
        fp.from_calibration(eye, [0.0, 40000.0, 0.0])
    assert err.value.status == Status.E_RANGE
    fp.from_calibration(eye, [0.0, -32768.0, 32768.0])  # the limits themselves are fine
    # row 2 = row 0 + row 1, every entry exact after quantisation
    singular = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [5.0, 7.0, 9.0]]) / 16
    with pytest.raises(fp.FixedPointError, match="singular") as err:
        fp.from_calibration(singular, zero)
    assert err.value.status == Status.E_SINGULAR
    with pytest.raises(fp.FixedPointError, match=r"condition number .* 1000 exceeds .* 100") as err:
        fp.from_calibration(np.diag([1.0, 1.0, 1e-3]), zero)
    assert err.value.status == Status.E_CONDITION
    fp.from_calibration(np.diag([1.0, 1.0, 1e-3]), zero, cond_max=1000)  # a device built so
    with pytest.raises(fp.FixedPointError, match=r"shift -1, outside .*out_exp in \[-14, 48\]"):
        fp.from_calibration(eye, zero, out_exp=-15)
    with pytest.raises(fp.FixedPointError, match=r"out_exp = 40 is outside") as err:
        fp.from_calibration(eye, zero, out_exp=40)
    assert err.value.status == Status.E_EXPONENT


def test_validate_errors_name_the_field():
    good = fp.from_calibration(np.eye(3), np.zeros(3))
    with pytest.raises(fp.FixedPointError, match="format version 2") as err:
        fp.validate(fp.DeviceParams(0, 15, good.d_inv, good.offset, version=2))
    assert err.value.status == Status.E_VERSION
    bad = list(good.d_inv)
    bad[5] = (1 << 30) + 1
    with pytest.raises(fp.FixedPointError, match=r"mantissa \[1\]\[2\] = 1073741825") as err:
        fp.validate(fp.DeviceParams(0, 15, tuple(bad), good.offset))
    assert err.value.status == Status.E_RANGE
    with pytest.raises(fp.FixedPointError, match="needs 9 and 3"):
        fp.validate(fp.DeviceParams(0, 15, good.d_inv[:8], good.offset))
    with pytest.raises(fp.FixedPointError, match="does not fit the encoding"):
        fp.encode(fp.DeviceParams(0, 15, good.d_inv, (1 << 31, 0, 0)))
