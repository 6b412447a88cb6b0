/* SPDX-License-Identifier: Apache-2.0 */
/* The parameter set: validation in exact integer arithmetic and the little-endian encoding.
 * See params.h. */
#include "magcal/params.h"

#include "magcal/fixed.h"

/* ---- unsigned 128-bit arithmetic from 32-bit limbs (portable C99, no library calls) ---- */

typedef struct {
    uint64_t hi, lo;
} u128_t;

/* a * b exactly. */
static u128_t u128_mul_u64(uint64_t a, uint64_t b)
{
    const uint64_t m32 = UINT64_C(0xFFFFFFFF);
    const uint64_t a0 = a & m32, a1 = a >> 32, b0 = b & m32, b1 = b >> 32;
    const uint64_t p00 = a0 * b0, p01 = a0 * b1, p10 = a1 * b0, p11 = a1 * b1;
    /* Middle column: three terms below 2^32 each, so no wrap. */
    const uint64_t mid = (p00 >> 32) + (p01 & m32) + (p10 & m32);
    u128_t r;
    r.lo = (mid << 32) | (p00 & m32);
    r.hi = p11 + (p01 >> 32) + (p10 >> 32) + (mid >> 32);
    return r;
}

static u128_t u128_add(u128_t a, u128_t b)
{
    u128_t r;
    r.lo = a.lo + b.lo;
    r.hi = a.hi + b.hi + (r.lo < a.lo ? 1u : 0u);
    return r;
}

/* a - b for a >= b. */
static u128_t u128_sub(u128_t a, u128_t b)
{
    u128_t r;
    r.lo = a.lo - b.lo;
    r.hi = a.hi - b.hi - (a.lo < b.lo ? 1u : 0u);
    return r;
}

/* -1, 0 or 1 as a <, == or > b. */
static int u128_cmp(u128_t a, u128_t b)
{
    if (a.hi != b.hi) {
        return a.hi < b.hi ? -1 : 1;
    }
    if (a.lo != b.lo) {
        return a.lo < b.lo ? -1 : 1;
    }
    return 0;
}

/* |x| for |x| <= 2^62 (never INT64_MIN here). */
static uint64_t abs_u64(int64_t x)
{
    return x < 0 ? (uint64_t)(-x) : (uint64_t)x;
}

static int32_t abs_i32_bounded(int32_t x, int32_t max_abs)
{
    /* -x would overflow for INT32_MIN; every value beyond max_abs is refused before that. */
    return (x < -max_abs || x > max_abs) ? -1 : (x < 0 ? -x : x);
}

/* The condition test of params.h on the mantissa matrix a (|a[k]| <= 2^30):
 * MC_E_SINGULAR, MC_E_CONDITION or MC_OK.
 *
 * Scaling and overflow: products of two entries are <= 2^60, so every 2x2 cofactor (a
 * difference of two) is <= 2^61 in magnitude and is exact in int64_t; a column sum of three
 * cofactors (||adj A||_inf) is < 2^63 and a row sum of |a| (||A||_inf) is < 2^32, both exact
 * in uint64_t. det A = sum a_0j C_0j has terms <= 2^91, summed exactly as 128-bit magnitudes
 * (positive and negative terms apart, < 2^93 each). ||A|| ||adj A|| < 2^95 and
 * MC_PARAMS_COND_MAX |det A| < 2^113 are exact 128-bit products. */
static mc_status_t check_conditioning(const int32_t a[9])
{
    int64_t c[9]; /* cofactor matrix, row-major: c[3 i + j] = (-1)^(i+j) minor_ij */
    c[0] = (int64_t)a[4] * a[8] - (int64_t)a[5] * a[7];
    c[1] = (int64_t)a[5] * a[6] - (int64_t)a[3] * a[8];
    c[2] = (int64_t)a[3] * a[7] - (int64_t)a[4] * a[6];
    c[3] = (int64_t)a[2] * a[7] - (int64_t)a[1] * a[8];
    c[4] = (int64_t)a[0] * a[8] - (int64_t)a[2] * a[6];
    c[5] = (int64_t)a[1] * a[6] - (int64_t)a[0] * a[7];
    c[6] = (int64_t)a[1] * a[5] - (int64_t)a[2] * a[4];
    c[7] = (int64_t)a[2] * a[3] - (int64_t)a[0] * a[5];
    c[8] = (int64_t)a[0] * a[4] - (int64_t)a[1] * a[3];

    /* det A along the first row: positive and negative terms summed apart. */
    u128_t pos = {0u, 0u}, neg = {0u, 0u};
    for (int j = 0; j < 3; ++j) {
        const int64_t aj = a[j];
        const u128_t t = u128_mul_u64(abs_u64(aj), abs_u64(c[j]));
        if ((aj < 0) != (c[j] < 0)) {
            neg = u128_add(neg, t);
        } else {
            pos = u128_add(pos, t);
        }
    }
    const int sign = u128_cmp(pos, neg);
    if (sign == 0) {
        return MC_E_SINGULAR;
    }
    const u128_t det_abs = sign > 0 ? u128_sub(pos, neg) : u128_sub(neg, pos);

    /* ||A||_inf: largest row sum of |a|; ||adj A||_inf: adj A = C^T, so the largest column
     * sum of |c|. */
    uint64_t norm_a = 0u, norm_adj = 0u;
    for (int i = 0; i < 3; ++i) {
        const uint64_t row = abs_u64(a[3 * i]) + abs_u64(a[3 * i + 1]) + abs_u64(a[3 * i + 2]);
        const uint64_t col = abs_u64(c[i]) + abs_u64(c[3 + i]) + abs_u64(c[6 + i]);
        norm_a = row > norm_a ? row : norm_a;
        norm_adj = col > norm_adj ? col : norm_adj;
    }
    const u128_t lhs = u128_mul_u64(norm_a, norm_adj);
    /* MC_PARAMS_COND_MAX |det A|: det_abs.hi < 2^29 and the bound is < 2^20, so the high
     * word's product cannot wrap. */
    const uint64_t k = (uint64_t)MC_PARAMS_COND_MAX;
    u128_t rhs = u128_mul_u64(det_abs.lo, k);
    rhs.hi += det_abs.hi * k;
    return u128_cmp(lhs, rhs) > 0 ? MC_E_CONDITION : MC_OK;
}

mc_status_t mc_params_validate(const mc_params_t *p)
{
    if (p == NULL) {
        return MC_E_ARG;
    }
    if (p->version != MC_PARAMS_FORMAT_VERSION) {
        return MC_E_VERSION;
    }
    const int e_d = p->d_inv_exp, e_m = p->out_exp;
    if (e_d < MC_PARAMS_EXP_MIN || e_d > MC_PARAMS_EXP_MAX || e_m < MC_PARAMS_EXP_MIN
        || e_m > MC_PARAMS_EXP_MAX) {
        return MC_E_EXPONENT;
    }
    const int shift = 14 + e_m - e_d;
    if (shift < 0 || shift > MC_PARAMS_SHIFT_MAX) {
        return MC_E_EXPONENT;
    }
    for (int k = 0; k < 9; ++k) {
        if (abs_i32_bounded(p->d_inv[k], MC_PARAMS_D_INV_MAX_ABS) < 0) {
            return MC_E_RANGE;
        }
    }
    for (int j = 0; j < 3; ++j) {
        if (abs_i32_bounded(p->offset[j], MC_PARAMS_OFFSET_MAX_ABS) < 0) {
            return MC_E_RANGE;
        }
    }
    return check_conditioning(p->d_inv);
}

/* ---- little-endian encoding ---- */

static void put_u32(uint8_t *b, uint32_t v)
{
    b[0] = (uint8_t)(v & 0xFFu);
    b[1] = (uint8_t)((v >> 8) & 0xFFu);
    b[2] = (uint8_t)((v >> 16) & 0xFFu);
    b[3] = (uint8_t)((v >> 24) & 0xFFu);
}

static uint32_t get_u32(const uint8_t *b)
{
    return (uint32_t)b[0] | ((uint32_t)b[1] << 8) | ((uint32_t)b[2] << 16)
        | ((uint32_t)b[3] << 24);
}

mc_status_t mc_params_encode(const mc_params_t *p, uint8_t *buf, size_t len, size_t *written)
{
    if (p == NULL || buf == NULL || written == NULL) {
        return MC_E_ARG;
    }
    *written = 0u;
    if (len < MC_PARAMS_ENCODED_SIZE) {
        return MC_E_NO_SPACE;
    }
    buf[0] = (uint8_t)(p->version & 0xFFu);
    buf[1] = (uint8_t)(p->version >> 8);
    buf[2] = (uint8_t)p->d_inv_exp; /* conversion to unsigned: well defined, mod 256 */
    buf[3] = (uint8_t)p->out_exp;
    for (int k = 0; k < 9; ++k) {
        put_u32(buf + 4 + 4 * k, (uint32_t)p->d_inv[k]);
    }
    for (int j = 0; j < 3; ++j) {
        put_u32(buf + 40 + 4 * j, (uint32_t)p->offset[j]);
    }
    *written = MC_PARAMS_ENCODED_SIZE;
    return MC_OK;
}

mc_status_t mc_params_decode(const uint8_t *buf, size_t len, mc_params_t *p)
{
    if (buf == NULL || p == NULL) {
        return MC_E_ARG;
    }
    if (len >= 2u) {
        const uint16_t version = (uint16_t)(buf[0] | (buf[1] << 8));
        if (version != MC_PARAMS_FORMAT_VERSION) {
            return MC_E_VERSION;
        }
    }
    if (len != MC_PARAMS_ENCODED_SIZE) {
        return MC_E_LENGTH;
    }
    mc_params_t q;
    q.version = MC_PARAMS_FORMAT_VERSION;
    q.d_inv_exp = mc_fx_i8_from_u8(buf[2]);
    q.out_exp = mc_fx_i8_from_u8(buf[3]);
    for (int k = 0; k < 9; ++k) {
        q.d_inv[k] = mc_fx_i32_from_u32(get_u32(buf + 4 + 4 * k));
    }
    for (int j = 0; j < 3; ++j) {
        q.offset[j] = mc_fx_i32_from_u32(get_u32(buf + 40 + 4 * j));
    }
    *p = q;
    return MC_OK;
}
