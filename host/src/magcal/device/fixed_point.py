# SPDX-License-Identifier: Apache-2.0
"""The device's fixed-point parameter set and correction, on the host.

Mirrors ``firmware/include/magcal/params.h`` and ``correction.h`` (read them for the
rationale); every function here is a pure function of its arguments.

Formats (format version 1), for the correction ``m = D_inv (y - o)`` on int16 raw counts y:

- ``d_inv``: 9 int32 mantissas, row-major, Q1.30 (``|d| <= 2**30``) scaled by the set's
  exponent ``E_d``: ``D_inv[i, j] = d_inv[3 i + j] * 2**(E_d - 30)``. ``E_d`` is the smallest
  exponent that holds the largest entry, so a unit-scale ``D_inv`` (entries about 1) and a
  counts-scale one (about 1/60 or 60) both keep 30 significant bits.
- ``offset``: 3 int32, raw counts in Q16.15 (``|offset| <= 2**30``, i.e. ±32768 counts).
- output: int32 ``m[i] = out[i] * 2**(E_m - 31)``, ``E_m = out_exp``, rounded to nearest (ties
  toward +inf) from the exact value, saturated to the int32 range.
  The default ``E_m`` (:func:`default_out_exp`) is the smallest for which no int16 input
  saturates and the parameters' quantisation moves no output by more than half an LSB, so
  that the output is within 1 LSB of the float64 correction with the unquantised D_inv and o.
- the device computes ``acc = sum_j d[i, j] (y_j 2**15 - offset_j)`` exactly in int64 and
  shifts right by ``s = 14 + E_m - E_d`` (0 <= s <= 62) with rounding.

The byte encoding (``mc_params_encode``, 52 bytes, little-endian): uint16 version, int8 E_d,
int8 E_m, int32 d_inv[9], int32 offset[3].

Validation (``validate``) is the device's ``mc_params_validate`` in exact Python integers; it
raises :class:`FixedPointError` whose ``status`` is the code the device would return.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from magcal.device.generated import Status
from magcal.errors import MagcalError

FORMAT_VERSION = 1  # MC_PARAMS_FORMAT_VERSION
ENCODED_SIZE = 52  # MC_PARAMS_ENCODED_SIZE
_ENCODING = struct.Struct("<Hbb9i3i")
assert _ENCODING.size == ENCODED_SIZE

D_INV_FRAC_BITS = 30  # MC_PARAMS_D_INV_FRAC_BITS
OFFSET_FRAC_BITS = 15  # MC_PARAMS_OFFSET_FRAC_BITS
D_INV_MAX_ABS = 1 << 30  # MC_PARAMS_D_INV_MAX_ABS
OFFSET_MAX_ABS = 1 << 30  # MC_PARAMS_OFFSET_MAX_ABS
EXP_MIN = -32  # MC_PARAMS_EXP_MIN
EXP_MAX = 32  # MC_PARAMS_EXP_MAX
SHIFT_MAX = 62  # MC_PARAMS_SHIFT_MAX
# The firmware's default MC_PARAMS_COND_MAX (config.h); pass cond_max= for a device built with
# another value.
COND_MAX = 100

INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
_FIXED_SHIFT_BASE = D_INV_FRAC_BITS + OFFSET_FRAC_BITS - 31  # s = 14 + E_m - E_d


class FixedPointError(MagcalError):
    """A calibration cannot be represented in the device's parameter format, or a parameter
    set or blob is invalid. ``status`` is the device status code for the same refusal."""

    def __init__(self, message: str, status: Status):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class DeviceParams:
    """The device's parameter set (``mc_params_t``), integers exactly as stored.

    d_inv : 9 ints, row-major Q1.30 mantissas of D_inv (scaled by 2**(d_inv_exp - 30))
    offset : 3 ints, o in raw counts, Q16.15
    d_inv_exp : E_d; out_exp : E_m (output m = out * 2**(out_exp - 31))
    """

    d_inv_exp: int
    out_exp: int
    d_inv: tuple[int, ...]
    offset: tuple[int, ...]
    version: int = FORMAT_VERSION

    @property
    def shift(self) -> int:
        """The device's rounding shift s = 14 + E_m - E_d."""
        return _FIXED_SHIFT_BASE + self.out_exp - self.d_inv_exp

    @property
    def out_lsb(self) -> float:
        """Size of one output LSB, in the calibration's output unit."""
        return math.ldexp(1.0, self.out_exp - 31)

    def d_inv_matrix(self) -> np.ndarray:
        """(3, 3) float64, D_inv exactly as stored (every entry is exact in float64)."""
        d = np.array(self.d_inv, dtype=np.float64).reshape(3, 3)
        return np.ldexp(d, self.d_inv_exp - D_INV_FRAC_BITS)

    def offset_counts(self) -> np.ndarray:
        """(3,) float64, o in raw counts exactly as stored."""
        return np.ldexp(np.array(self.offset, dtype=np.float64), -OFFSET_FRAC_BITS)


# ---------------------------------------------------------------- validation


def _det_and_norms(a: tuple[int, ...]) -> tuple[int, int, int]:
    """det A, ||A||_inf and ||adj A||_inf of the mantissa matrix, exact (as params.c)."""
    c = [  # cofactors, row-major: c[3 i + j] = (-1)**(i + j) minor_ij
        a[4] * a[8] - a[5] * a[7],
        a[5] * a[6] - a[3] * a[8],
        a[3] * a[7] - a[4] * a[6],
        a[2] * a[7] - a[1] * a[8],
        a[0] * a[8] - a[2] * a[6],
        a[1] * a[6] - a[0] * a[7],
        a[1] * a[5] - a[2] * a[4],
        a[2] * a[3] - a[0] * a[5],
        a[0] * a[4] - a[1] * a[3],
    ]
    det = a[0] * c[0] + a[1] * c[1] + a[2] * c[2]
    norm_a = max(abs(a[3 * i]) + abs(a[3 * i + 1]) + abs(a[3 * i + 2]) for i in range(3))
    # adj A = C^T: its row sums are the column sums of |C|.
    norm_adj = max(abs(c[i]) + abs(c[3 + i]) + abs(c[6 + i]) for i in range(3))
    return det, norm_a, norm_adj


def condition_inf(d_inv: tuple[int, ...]) -> float:
    """kappa_inf = ||A||_inf ||A^-1||_inf of the mantissa matrix A (inf when singular),
    from exact integers. The device refuses kappa_inf > cond_max (MC_E_CONDITION)."""
    det, norm_a, norm_adj = _det_and_norms(tuple(d_inv))
    return math.inf if det == 0 else norm_a * norm_adj / abs(det)


def _check_format(p: DeviceParams) -> None:
    """Version, exponents and ranges: what makes the device's arithmetic exact."""
    if p.version != FORMAT_VERSION:
        raise FixedPointError(
            f"parameter set has format version {p.version}; this device format is version "
            f"{FORMAT_VERSION}: convert the calibration again with this magcal",
            Status.E_VERSION,
        )
    for name, e in (("d_inv_exp", p.d_inv_exp), ("out_exp", p.out_exp)):
        if not EXP_MIN <= e <= EXP_MAX:
            raise FixedPointError(
                f"parameter set's {name} = {e} is outside the device's [{EXP_MIN}, {EXP_MAX}]",
                Status.E_EXPONENT,
            )
    if not 0 <= p.shift <= SHIFT_MAX:
        lo = p.d_inv_exp - _FIXED_SHIFT_BASE
        raise FixedPointError(
            f"output exponent {p.out_exp} with D_inv exponent {p.d_inv_exp} gives the shift "
            f"{p.shift}, outside the device's [0, {SHIFT_MAX}]: choose out_exp in "
            f"[{lo}, {lo + SHIFT_MAX}]",
            Status.E_EXPONENT,
        )
    if len(p.d_inv) != 9 or len(p.offset) != 3:
        raise FixedPointError(
            f"parameter set has {len(p.d_inv)} D_inv entries and {len(p.offset)} offsets; "
            "it needs 9 and 3",
            Status.E_RANGE,
        )
    for k, d in enumerate(p.d_inv):
        if abs(d) > D_INV_MAX_ABS:
            raise FixedPointError(
                f"D_inv mantissa [{k // 3}][{k % 3}] = {d} is beyond ±2^30", Status.E_RANGE
            )
    for j, o in enumerate(p.offset):
        if abs(o) > OFFSET_MAX_ABS:
            raise FixedPointError(
                f"offset o[{j}] = {math.ldexp(o, -OFFSET_FRAC_BITS):.6g} counts is beyond the "
                "device's ±32768 counts: the calibration's offset must be in raw counts",
                Status.E_RANGE,
            )


def validate(params: DeviceParams, *, cond_max: int = COND_MAX) -> None:
    """Check ``params`` as the device's ``mc_params_validate`` does, in the same order.

    Raises FixedPointError with status E_VERSION, E_EXPONENT, E_RANGE, E_SINGULAR or
    E_CONDITION. Exact integers, so the verdict is the device's, bit for bit.
    """
    _check_format(params)
    det, norm_a, norm_adj = _det_and_norms(tuple(params.d_inv))
    if det == 0:
        raise FixedPointError(
            "D_inv is singular (determinant exactly 0 after quantisation): the calibration "
            "is unusable; calibrate again with more rotation",
            Status.E_SINGULAR,
        )
    # The device's exact test: ||A|| ||adj A|| <= cond_max |det A|.
    if norm_a * norm_adj > cond_max * abs(det):
        raise FixedPointError(
            f"D_inv is too badly conditioned: its condition number (inf-norm) "
            f"{norm_a * norm_adj / abs(det):.4g} exceeds the device's limit {cond_max}; "
            "check the calibration (too little rotation?)",
            Status.E_CONDITION,
        )


# ---------------------------------------------------------------- conversion


def _exponent_for(max_abs: float) -> int:
    """Smallest E with max_abs <= 2**E (max_abs > 0, finite)."""
    mant, e = math.frexp(max_abs)  # max_abs = mant 2**e, mant in [0.5, 1)
    return e - 1 if mant == 0.5 else e


def _acc_extremes(d_inv: tuple[int, ...], offset: tuple[int, ...]) -> tuple[int, int]:
    """The smallest and largest accumulator of any output row over every int16 input, exact
    (each input axis is free, so a row's extremes are sums of per-term extremes)."""
    diff_min = [INT16_MIN * 32768 - o for o in offset]
    diff_max = [INT16_MAX * 32768 - o for o in offset]
    acc_max = acc_min = 0
    for i in range(3):
        terms = [(d_inv[3 * i + j] * diff_min[j], d_inv[3 * i + j] * diff_max[j]) for j in range(3)]
        acc_max = max(acc_max, sum(max(t) for t in terms))
        acc_min = min(acc_min, sum(min(t) for t in terms))
    return acc_min, acc_max


def quantisation_error_bound(
    d_inv_exp: int,
    d_inv: tuple[int, ...],
    offset: tuple[int, ...],
    d_inv_exact,
    offset_exact,
) -> Fraction:
    """The largest |D_q (y - o_q) - D (y - o)| over every output row and every int16 input y,
    exactly, in the output's unit: what quantising the parameters costs.

    d_inv_exp, d_inv, offset : the stored set (D_q, o_q)
    d_inv_exact : 9 numbers (row-major) or a (3, 3) array, the unquantised D_inv in raw counts
    offset_exact : 3 numbers, the unquantised o in raw counts
    (floats, ints or Fractions; every float is taken at its exact value).

    Per row i the error is affine in y: with dD = D_q - D,
        e_i(y) = sum_j dD_ij (y_j - o_q,j) + sum_j D_ij (o_j - o_q,j),
    so its largest magnitude over the box y in [-32768, 32767]^3 is reached at a corner
    (sum of the per-axis extremes of the first part, plus the constant) and is exact here.
    """
    d_ex = [Fraction(v) for v in np.asarray(d_inv_exact, dtype=object).ravel()]
    o_ex = [Fraction(v) for v in np.asarray(offset_exact, dtype=object).ravel()]
    if len(d_ex) != 9 or len(o_ex) != 3:
        raise FixedPointError("the unquantised D_inv needs 9 entries and o 3", Status.E_ARG)
    d_q = [Fraction(m) * Fraction(2) ** (d_inv_exp - D_INV_FRAC_BITS) for m in d_inv]
    o_q = [Fraction(m, 1 << OFFSET_FRAC_BITS) for m in offset]
    worst = Fraction(0)
    for i in range(3):
        row = range(3 * i, 3 * i + 3)
        const = sum(d_ex[k] * (o_ex[k - 3 * i] - o_q[k - 3 * i]) for k in row)
        hi = lo = const
        for k in row:
            j = k - 3 * i
            a, b = (
                (d_q[k] - d_ex[k]) * (INT16_MIN - o_q[j]),
                (d_q[k] - d_ex[k]) * (INT16_MAX - o_q[j]),
            )
            hi += max(a, b)
            lo += min(a, b)
        worst = max(worst, abs(hi), abs(lo))
    return worst


#: The share of an output LSB that the default output exponent allows the parameters'
#: quantisation error: half an LSB less 2**-16 LSB, the room left for evaluating the host's
#: float64 correction (its rounding errors are below 2**-18 LSB for a set that cannot saturate).
PARAM_ERROR_BUDGET_LSB = Fraction(1, 2) - Fraction(1, 1 << 16)


def default_out_exp(
    d_inv_exp: int,
    d_inv: tuple[int, ...],
    offset: tuple[int, ...],
    *,
    d_inv_exact=None,
    offset_exact=None,
) -> int:
    """The default output exponent E_m: the smallest E_m (within the device's limits) such that

    (a) no int16 input saturates any output (exact, from the integer worst case of the
        accumulator), and
    (b) quantising the parameters moves no output by more than half an LSB (less 2**-16 LSB)
        for any int16 input: ``quantisation_error_bound(...) <= PARAM_ERROR_BUDGET_LSB *
        2**(E_m - 31)``, computed exactly from the actual quantisation errors of the D_inv
        mantissas and the offset against the unquantised ``d_inv_exact`` and ``offset_exact``
        (raw counts; see :func:`quantisation_error_bound`). Without them, (b) is void: the
        stored set is taken as the calibration itself.

    Why: the device returns ``round(D_q (y - o_q))`` exactly rounded once, so when not
    saturated ``|out - D_q (y - o_q)| <= 1/2`` LSB; with (b) ``|D_q (y - o_q) - D (y - o)| <=
    1/2 - 2**-16`` LSB; hence ``|out - D (y - o)| <= 1 - 2**-16`` LSB for every int16 input,
    and a float64 evaluation of ``D (y - o)`` (error below 2**-18 LSB: three products of at
    most about 2**32 LSB in all) still sees at most 1 LSB. Both conditions only get easier as
    E_m grows, so the smallest one is the finest output that keeps the guarantee.

    Cost: over every int16 input, |dD_ij| <= 2**(E_d - 31) meets |y_j - o_q,j| up to 2**16,
    so the mantissas' rounding dominates (the offset's 2**-16-count error adds a third);
    (b) usually costs 1 to 3 exponent steps over (a) alone (0 when the parameters are exact).
    A ceiling: the error is at most about 3 2**(E_d - 15) + 3 2**(E_d - 16) = 9 2**(E_d - 16)
    (|D_ij| <= 2**E_d, |dD_ij| <= 2**(E_d - 31), |o_j - o_q,j| <= 2**-16), so E_m = E_d + 20
    always meets (b) (it needs 2**(E_m - E_d) >= 18 2**15 / (1 - 2**-15) < 2**20), and
    E_m <= max(E_m of (a), E_d + 20); as (a) needs E_m >= E_d + 14 (the largest mantissa is
    >= 2**29 and one extreme of its input gives |y 2**15 - offset| >= 2**30 - 2**15), that is
    at most 6 steps (seen: up to 4, on extreme matrices).

    An explicit E_m finer than this default (``from_calibration(out_exp=...)``) is the
    caller's choice and has no such guarantee. When no allowed E_m satisfies both, the
    largest allowed one is returned (no guarantee).
    """
    lo = max(EXP_MIN, d_inv_exp - _FIXED_SHIFT_BASE)
    hi = min(EXP_MAX, d_inv_exp - _FIXED_SHIFT_BASE + SHIFT_MAX)
    acc_min, acc_max = _acc_extremes(d_inv, offset)
    if d_inv_exact is None and offset_exact is None:
        err = Fraction(0)
    else:
        if d_inv_exact is None or offset_exact is None:
            raise FixedPointError(
                "give both d_inv_exact and offset_exact, or neither", Status.E_ARG
            )
        err = quantisation_error_bound(d_inv_exp, d_inv, offset, d_inv_exact, offset_exact)
    for e_m in range(lo, hi + 1):
        s = _FIXED_SHIFT_BASE + e_m - d_inv_exp
        if _round_shift_int(acc_max, s) > INT32_MAX or _round_shift_int(acc_min, s) < INT32_MIN:
            continue
        if err <= PARAM_ERROR_BUDGET_LSB * Fraction(2) ** (e_m - 31):
            return e_m
    return hi


def param_error_lsb(
    params: DeviceParams, d_inv: np.ndarray, o: np.ndarray, *, unit_per_count: float = 1.0
) -> float:
    """The largest |D_q (y - o_q) - D (y - o)| over every int16 input, in ``params``' output
    LSBs, for the calibration ``(d_inv, o, unit_per_count)`` as :func:`from_calibration`
    takes it (exact, rounded to float at the end). At most 1/2 - 2**-16 for a set built with
    the default output exponent."""
    d_ex, o_ex = _exact_counts(d_inv, o, unit_per_count)
    err = quantisation_error_bound(params.d_inv_exp, params.d_inv, params.offset, d_ex, o_ex)
    return float(err * Fraction(2) ** (31 - params.out_exp))


def _exact_counts(d_inv, o, unit_per_count: float) -> tuple[list[Fraction], list[Fraction]]:
    """D_inv * u and o / u as exact rationals of the given floats (raw counts)."""
    u = Fraction(float(unit_per_count))
    d = [Fraction(float(v)) * u for v in np.asarray(d_inv, dtype=np.float64).ravel()]
    off = [Fraction(float(v)) / u for v in np.asarray(o, dtype=np.float64).ravel()]
    return d, off


def from_calibration(
    d_inv: np.ndarray,
    o: np.ndarray,
    *,
    unit_per_count: float = 1.0,
    out_exp: int | None = None,
    cond_max: int = COND_MAX,
) -> DeviceParams:
    """The device parameter set for the calibration ``m = d_inv (y - o)``.

    d_inv : (3, 3) float, the result's ``D_inv`` (per session unit)
    o : (3,) float, the result's ``o``, session unit
    unit_per_count : float, size of one raw count in the session's unit (1 when the session
        was recorded in raw counts): the device corrects counts, so D_inv is scaled by it and o
        divided by it
    out_exp : int, output exponent E_m; default (:func:`default_out_exp`): the smallest for
        which no int16 input saturates and the device's output is within 1 LSB of the float
        correction ``d_inv (y u - o)`` with these unquantised values, for every int16 input y
        (u = unit_per_count). An explicit out_exp is used as given (any the device accepts): a
        finer one than the default carries no such guarantee (the parameters' quantisation
        may then exceed half an LSB, or outputs saturate)
    cond_max : the device's MC_PARAMS_COND_MAX

    Returns DeviceParams, validated. Raises FixedPointError naming the problem when the
    calibration cannot be represented or the device would refuse it.
    """
    d = np.asarray(d_inv, dtype=np.float64)
    off = np.asarray(o, dtype=np.float64)
    if d.shape != (3, 3) or off.shape != (3,):
        raise FixedPointError(
            f"D_inv must be 3x3 and o a 3-vector; got shapes {d.shape} and {off.shape}",
            Status.E_ARG,
        )
    if not (math.isfinite(unit_per_count) and unit_per_count > 0):
        raise FixedPointError(
            f"unit_per_count must be a positive number, got {unit_per_count!r}", Status.E_ARG
        )
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(off))):
        raise FixedPointError(
            "D_inv or o has a non-finite entry (NaN or inf): the calibration is unusable",
            Status.E_RANGE,
        )
    d = d * unit_per_count
    off = off / unit_per_count
    max_abs = float(np.max(np.abs(d)))
    if max_abs == 0.0:
        raise FixedPointError("D_inv is all zeros, which is singular", Status.E_SINGULAR)
    e_d = _exponent_for(max_abs)
    if not EXP_MIN <= e_d <= EXP_MAX:
        raise FixedPointError(
            f"D_inv's largest entry {max_abs:.4g} needs the exponent {e_d}, outside the "
            f"device's [{EXP_MIN}, {EXP_MAX}]: is D_inv in raw counts (see unit_per_count)?",
            Status.E_EXPONENT,
        )
    # Round to nearest; |mantissa| <= 2**30 since max_abs <= 2**E_d.
    mant = tuple(int(v) for v in np.rint(np.ldexp(d, D_INV_FRAC_BITS - e_d)).ravel())
    offset_q = np.rint(np.ldexp(off, OFFSET_FRAC_BITS))
    for j in range(3):
        if abs(offset_q[j]) > OFFSET_MAX_ABS:
            raise FixedPointError(
                f"offset o[{j}] = {off[j]:.6g} counts is beyond the device's ±32768 counts: "
                "the calibration's offset must be in raw counts (see unit_per_count)",
                Status.E_RANGE,
            )
    offset = tuple(int(v) for v in offset_q)
    if out_exp is None:
        d_ex, o_ex = _exact_counts(d_inv, o, unit_per_count)
        out_exp = default_out_exp(e_d, mant, offset, d_inv_exact=d_ex, offset_exact=o_ex)
    params = DeviceParams(d_inv_exp=e_d, out_exp=int(out_exp), d_inv=mant, offset=offset)
    validate(params, cond_max=cond_max)
    return params


# ---------------------------------------------------------------- encoding


def encode(params: DeviceParams) -> bytes:
    """The 52 bytes of ``mc_params_encode`` (does not validate; field sizes are checked)."""
    p = params
    try:
        return _ENCODING.pack(p.version, p.d_inv_exp, p.out_exp, *p.d_inv, *p.offset)
    except struct.error as exc:
        raise FixedPointError(
            f"parameter set does not fit the encoding's field sizes: {exc}", Status.E_RANGE
        ) from exc


def decode(blob: bytes) -> DeviceParams:
    """The parameter set in ``blob`` (as ``mc_params_decode``: E_VERSION for another format
    version, E_LENGTH for a wrong size; values are not validated)."""
    if len(blob) >= 2:
        (version,) = struct.unpack_from("<H", blob)
        if version != FORMAT_VERSION:
            raise FixedPointError(
                f"parameter blob has format version {version}; this magcal reads version "
                f"{FORMAT_VERSION}",
                Status.E_VERSION,
            )
    if len(blob) != ENCODED_SIZE:
        raise FixedPointError(
            f"parameter blob has {len(blob)} bytes; format version {FORMAT_VERSION} has "
            f"{ENCODED_SIZE}",
            Status.E_LENGTH,
        )
    fields = _ENCODING.unpack(blob)
    return DeviceParams(
        version=fields[0],
        d_inv_exp=fields[1],
        out_exp=fields[2],
        d_inv=tuple(fields[3:12]),
        offset=tuple(fields[12:15]),
    )


# ---------------------------------------------------------------- correction


def _round_shift_int(x: int, s: int) -> int:
    """floor(x / 2**s + 1/2) for Python ints."""
    return x if s == 0 else ((x >> (s - 1)) + 1) >> 1


def _raw_array(raw: np.ndarray) -> np.ndarray:
    y = np.asarray(raw)
    if y.ndim != 2 or y.shape[1] != 3:
        raise FixedPointError(f"raw must be (N, 3); got shape {y.shape}", Status.E_ARG)
    if y.size and (y.min() < INT16_MIN or y.max() > INT16_MAX):
        raise FixedPointError("raw counts must be int16 values", Status.E_RANGE)
    return y.astype(np.int64)


def emulate(params: DeviceParams, raw: np.ndarray) -> np.ndarray:
    """The device's output for raw, bit-exact.

    raw : (N, 3) int, raw counts (int16 range). Returns (N, 3) int32 in the output format.
    The accumulator is exact in int64 (|acc| <= 3 2**61, see correction.h).
    """
    _check_format(params)  # the bounds that make the int64 accumulator exact
    y = _raw_array(raw)
    diff = y * 32768 - np.array(params.offset, dtype=np.int64)
    d = np.array(params.d_inv, dtype=np.int64).reshape(3, 3)
    acc = diff[:, 0:1] * d[:, 0] + diff[:, 1:2] * d[:, 1] + diff[:, 2:3] * d[:, 2]
    s = params.shift
    # floor((acc / 2**(s-1) + 1) / 2): numpy's >> on int64 is an arithmetic (floor) shift.
    rounded = acc if s == 0 else ((acc >> (s - 1)) + 1) >> 1
    return np.clip(rounded, INT32_MIN, INT32_MAX).astype(np.int32)


def reference_lsb(params: DeviceParams, raw: np.ndarray) -> np.ndarray:
    """float64 reference of D_inv (y - o) for the stored parameters, in output LSBs,
    unrounded and unclipped.

    raw : (N, 3) int, raw counts. Returns (N, 3) float64.

    Accuracy: each product d (y - o) is split into two products that are exact in float64
    (d = dh 2**15 + dl, |dh| <= 2**15, 0 <= dl < 2**15, and y 2**15 - offset < 2**32), and the
    six are summed with Neumaier's compensated sum, so the result is within about 2**-52 of
    itself plus 2**-100 of the terms: a plain ``D_inv @ (y - o)`` would lose up to 2**-53 of
    the largest product, which matters for outputs that nearly cancel.
    """
    y = _raw_array(raw).astype(np.float64)
    diff = y * 32768.0 - np.array(params.offset, dtype=np.float64)  # exact integers
    d = np.array(params.d_inv, dtype=np.float64).reshape(3, 3)
    dh = np.floor(d / 32768.0)
    dl = d - dh * 32768.0
    total = np.zeros((y.shape[0], 3))
    comp = np.zeros((y.shape[0], 3))
    for j in range(3):
        for term in (diff[:, j : j + 1] * dh[:, j] * 32768.0, diff[:, j : j + 1] * dl[:, j]):
            s = total + term
            bb = s - total
            comp += (total - (s - bb)) + (term - bb)
            total = s
    return np.ldexp(total + comp, -params.shift)


def reference(params: DeviceParams, raw: np.ndarray) -> np.ndarray:
    """float64 reference of m = D_inv (y - o) in the calibration's output unit (unit norm
    for a counts-scale calibration), for the stored (quantised) parameters.

    raw : (N, 3) int, raw counts. Returns (N, 3) float64.
    """
    return np.ldexp(reference_lsb(params, raw), params.out_exp - 31)


def output_to_float(params: DeviceParams, out: np.ndarray) -> np.ndarray:
    """The device's int32 outputs (N, 3) as float64 values of m (exact)."""
    return np.ldexp(np.asarray(out, dtype=np.float64), params.out_exp - 31)
