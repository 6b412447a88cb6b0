/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Fixed-point helpers shared by the firmware modules: saturation, round-to-nearest right
 * shifts and the two's-complement conversions between unsigned and signed integers, all
 * well defined in C99 for every input (no shift of a negative value, no signed overflow, no
 * implementation-defined unsigned-to-signed conversion). They are static inline and call no
 * library function: on a Cortex-M4 they compile to a few instructions (64-bit shifts, adds
 * and compares only, no division).
 *
 * Rounding: mc_fx_rshift_round_i64 rounds to nearest with ties toward +infinity
 * (floor(x / 2^s + 1/2)), the rule of "add half an LSB, then shift" that CMSIS-DSP uses; it is
 * exact (the result is the integer nearest to the exact quotient).
 */
#ifndef MAGCAL_FIXED_H
#define MAGCAL_FIXED_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The int64_t whose two's-complement bit pattern is u (u mod 2^64 read as signed), without
 * the implementation-defined conversion of an out-of-range value. Compilers reduce it to
 * nothing. */
static inline int64_t mc_fx_i64_from_u64(uint64_t u)
{
    if (u <= (uint64_t)INT64_MAX) {
        return (int64_t)u;
    }
    return -(int64_t)(UINT64_MAX - u) - 1;
}

/* The int32_t whose two's-complement bit pattern is u (used when decoding little-endian
 * bytes). */
static inline int32_t mc_fx_i32_from_u32(uint32_t u)
{
    if (u <= (uint32_t)INT32_MAX) {
        return (int32_t)u;
    }
    return -(int32_t)(UINT32_MAX - u) - 1;
}

/* The int8_t whose two's-complement bit pattern is u. */
static inline int8_t mc_fx_i8_from_u8(uint8_t u)
{
    return u <= 127u ? (int8_t)u : (int8_t)((int)u - 256);
}

/*
 * x clipped to [INT32_MIN, INT32_MAX].
 *
 * Scaling and overflow: the same scale in and out (no shift, no rounding): a value that fits
 * int32_t is returned unchanged, one beyond a limit becomes that limit (saturation, never a
 * wrap). Defined for every int64_t, INT64_MIN and INT64_MAX included; only comparisons and an
 * in-range conversion. Tested at both int64 extremes and one past each int32 limit
 * (test_fw_correction.c).
 */
static inline int32_t mc_fx_sat_i32(int64_t x)
{
    if (x > INT32_MAX) {
        return INT32_MAX;
    }
    if (x < INT32_MIN) {
        return INT32_MIN;
    }
    return (int32_t)x;
}

/*
 * x clipped to [INT16_MIN, INT16_MAX].
 *
 * Scaling and overflow: as mc_fx_sat_i32, for int16_t: unchanged in range, the nearest limit
 * beyond it, defined for every int64_t. Tested past both limits and at INT16_MIN
 * (test_fw_correction.c).
 */
static inline int16_t mc_fx_sat_i16(int64_t x)
{
    if (x > INT16_MAX) {
        return INT16_MAX;
    }
    if (x < INT16_MIN) {
        return INT16_MIN;
    }
    return (int16_t)x;
}

/*
 * floor(x / 2^s): an arithmetic right shift that is defined for negative x. Requires
 * 0 <= s <= 63 (the caller guarantees it; larger s is clamped to 63).
 *
 * Scaling and overflow: the result has magnitude <= 2^(63-s), so it never overflows. It works
 * on u = x + 2^63 (mod 2^64, computed in uint64_t: u is in [0, 2^64) and is x's bit pattern
 * with the top bit flipped): floor(u / 2^s) = floor(x / 2^s) + 2^(63-s) because 2^s divides
 * 2^63.
 */
static inline int64_t mc_fx_rshift_floor_i64(int64_t x, unsigned s)
{
    if (s == 0u) {
        return x;
    }
    if (s > 63u) {
        s = 63u;
    }
    const uint64_t u = (uint64_t)x ^ (UINT64_C(1) << 63);
    return mc_fx_i64_from_u64((u >> s) - (UINT64_C(1) << (63u - s)));
}

/*
 * round(x / 2^s) to nearest, ties toward +infinity: floor(x / 2^s + 1/2). Requires
 * 0 <= s <= 63 (larger s is clamped to 63).
 *
 * Scaling and overflow: works for every int64_t x, including INT64_MIN and INT64_MAX (the
 * "add half" is never formed in a signed type). With u = x + 2^63 as above and
 * u = q 2^s + r, the rounded quotient is q + (r >= 2^(s-1)) = (u >> s) + bit s-1 of u, at most
 * 2^(64-s) <= 2^63 for s >= 1, so the unsigned sum cannot wrap; subtracting 2^(63-s) gives
 * round(x / 2^s), of magnitude <= 2^(63-s), which fits int64_t.
 */
static inline int64_t mc_fx_rshift_round_i64(int64_t x, unsigned s)
{
    if (s == 0u) {
        return x;
    }
    if (s > 63u) {
        s = 63u;
    }
    const uint64_t u = (uint64_t)x ^ (UINT64_C(1) << 63);
    const uint64_t q = (u >> s) + ((u >> (s - 1u)) & 1u);
    return mc_fx_i64_from_u64(q - (UINT64_C(1) << (63u - s)));
}

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_FIXED_H */
