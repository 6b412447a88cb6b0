/* SPDX-License-Identifier: Apache-2.0 */
/* The fixed-point correction: argument and state errors, validation refusals through init,
 * the fixed.h helpers on their edge cases, known values and ties, forced saturation at the
 * extremes of every input and parameter, and 10^6 random cases against two references:
 *
 *  - a float64 reference of D^-1 (y - o) for the stored parameters, computed accurately
 *    (each product split into two exact float64 products, the six summed with Neumaier's
 *    compensated sum, error < 2^-20 LSB), then clipped to the output range. Criterion
 *    (the requirement): |out - clip(ref)| <= 1 LSB. Design property, also asserted:
 *    |out - ref| <= 1/2 LSB (+ 2^-20) when not saturated, since the device rounds the exact
 *    value once.
 *  - where long double holds 64-bit integers exactly (x86-64, LDBL_MANT_DIG >= 64): the exact
 *    value rounded half up and saturated, compared bit for bit.
 */
#include "check.h"
#include "magcal/correction.h"
#include "magcal/fixed.h"

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define T30 (INT32_C(1) << 30)

static uint64_t rng_state = 12345u;

/* splitmix64 */
static uint64_t rng_next(void)
{
    uint64_t z = (rng_state += UINT64_C(0x9E3779B97F4A7C15));
    z = (z ^ (z >> 30)) * UINT64_C(0xBF58476D1CE4E5B9);
    z = (z ^ (z >> 27)) * UINT64_C(0x94D049BB133111EB);
    return z ^ (z >> 31);
}

static double rng_unit(void)
{
    return (double)(rng_next() >> 11) * 0x1.0p-53;
}

/* uniform integer in [lo, hi] */
static int64_t rng_int(int64_t lo, int64_t hi)
{
    return lo + (int64_t)(rng_next() % (uint64_t)(hi - lo + 1));
}

static mc_params_t make_params(int e_d, int e_m, const int32_t d[9], const int32_t o[3])
{
    mc_params_t p;
    memset(&p, 0, sizeof p);
    p.version = MC_PARAMS_FORMAT_VERSION;
    p.d_inv_exp = (int8_t)e_d;
    p.out_exp = (int8_t)e_m;
    memcpy(p.d_inv, d, sizeof p.d_inv);
    memcpy(p.offset, o, sizeof p.offset);
    return p;
}

/* ---- references ---- */

static void two_sum(double a, double b, double *s, double *e)
{
    *s = a + b;
    const double bb = *s - a;
    *e = (a - (*s - bb)) + (b - bb);
}

/* D^-1 (y - o) for axis i in output LSBs (unclipped), in float64: d = dh 2^15 + dl with
 * |dh| <= 2^15, 0 <= dl < 2^15; dh diff and dl diff are exact (< 2^47); the six terms are
 * summed with a compensated sum. */
static double ref_lsb(const mc_params_t *p, const int16_t y[3], int i)
{
    double sum = 0.0, comp = 0.0;
    for (int j = 0; j < 3; ++j) {
        const double diff = (double)y[j] * 32768.0 - (double)p->offset[j]; /* exact */
        const double d = (double)p->d_inv[3 * i + j];
        const double dh = floor(d / 32768.0);
        const double dl = d - dh * 32768.0;
        const double terms[2] = {dh * diff * 32768.0, dl * diff};
        for (int t = 0; t < 2; ++t) {
            double s, e;
            two_sum(sum, terms[t], &s, &e);
            sum = s;
            comp += e;
        }
    }
    /* acc has 45 - E_d fractional bits, the output 31 - E_m: scale by 2^-(14 + E_m - E_d) */
    return ldexp(sum + comp, -(14 + p->out_exp - p->d_inv_exp));
}

static double clip_out(double x)
{
    return x > (double)INT32_MAX ? (double)INT32_MAX : x < (double)INT32_MIN ? (double)INT32_MIN : x;
}

#if LDBL_MANT_DIG >= 64
#define HAVE_EXACT_REF 1
/* The exact value rounded half up and saturated, in long double (products < 2^62 and sums
 * < 2^63 of integers are exact with a 64-bit significand). */
static int32_t exact_out(const mc_params_t *p, const int16_t y[3], int i)
{
    long double acc = 0.0L;
    for (int j = 0; j < 3; ++j) {
        const long double diff = (long double)y[j] * 32768.0L - (long double)p->offset[j];
        acc += (long double)p->d_inv[3 * i + j] * diff;
    }
    const long double q = ldexpl(acc, -(14 + p->out_exp - p->d_inv_exp));
    const long double fl = floorl(q);
    const long double r = fl + ((q - fl) >= 0.5L ? 1.0L : 0.0L);
    if (r > (long double)INT32_MAX) {
        return INT32_MAX;
    }
    if (r < (long double)INT32_MIN) {
        return INT32_MIN;
    }
    return (int32_t)r;
}
#else
#define HAVE_EXACT_REF 0
#endif

/* ---- tests ---- */

static void test_fixed_helpers(void)
{
    CHECK_EQ_INT(mc_fx_sat_i32(INT64_MAX), INT32_MAX);
    CHECK_EQ_INT(mc_fx_sat_i32(INT64_MIN), INT32_MIN);
    CHECK_EQ_INT(mc_fx_sat_i32((int64_t)INT32_MAX + 1), INT32_MAX);
    CHECK_EQ_INT(mc_fx_sat_i32((int64_t)INT32_MIN - 1), INT32_MIN);
    CHECK_EQ_INT(mc_fx_sat_i32(INT32_MAX), INT32_MAX);
    CHECK_EQ_INT(mc_fx_sat_i32(-5), -5);
    CHECK_EQ_INT(mc_fx_sat_i16(40000), INT16_MAX);
    CHECK_EQ_INT(mc_fx_sat_i16(-40000), INT16_MIN);
    CHECK_EQ_INT(mc_fx_sat_i16(-32768), -32768);
    CHECK_EQ_INT(mc_fx_i64_from_u64(UINT64_MAX), -1);
    CHECK_EQ_INT(mc_fx_i64_from_u64(UINT64_C(1) << 63), INT64_MIN);
    CHECK_EQ_INT(mc_fx_i32_from_u32(0x80000000u), INT32_MIN);
    CHECK_EQ_INT(mc_fx_i32_from_u32(0xFFFFFFFEu), -2);
    CHECK_EQ_INT(mc_fx_i32_from_u32(0x7FFFFFFFu), INT32_MAX);
    CHECK_EQ_INT(mc_fx_i8_from_u8(0x80u), -128);
    CHECK_EQ_INT(mc_fx_i8_from_u8(0x7Fu), 127);

    /* round half up and floor, around ties, at the int64 extremes and every shift */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(1, 1), 1);   /* 0.5 -> 1 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-1, 1), 0);  /* -0.5 -> 0 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(3, 1), 2);   /* 1.5 -> 2 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-3, 1), -1); /* -1.5 -> -1 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-5, 2), -1); /* -1.25 -> -1 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-7, 2), -2); /* -1.75 -> -2 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-6, 2), -1); /* -1.5 -> -1 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MAX, 1), INT64_C(1) << 62);
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MIN, 1), -(INT64_C(1) << 62));
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MAX, 63), 1);
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MIN, 63), -1);
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MIN, 200), -1); /* clamped to 63 */
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MAX, 62), 2);
    CHECK_EQ_INT(mc_fx_rshift_round_i64(INT64_MIN, 62), -2);
    CHECK_EQ_INT(mc_fx_rshift_round_i64(-12345, 0), -12345);
    CHECK_EQ_INT(mc_fx_rshift_floor_i64(-1, 1), -1);
    CHECK_EQ_INT(mc_fx_rshift_floor_i64(-3, 1), -2);
    CHECK_EQ_INT(mc_fx_rshift_floor_i64(INT64_MIN, 63), -1);
    CHECK_EQ_INT(mc_fx_rshift_floor_i64(INT64_MAX, 63), 0);
    CHECK_EQ_INT(mc_fx_rshift_floor_i64(7, 0), 7);
    int bad = 0;
    for (unsigned s = 1; s <= 63u; ++s) {
        for (int n = 0; n < 2000; ++n) {
            int64_t x = (int64_t)rng_next();
            if (n < 8) { /* the extremes and the ties around 0 */
                const int64_t edge[8] = {INT64_MIN, INT64_MAX, 0, -1, 1, INT64_MIN + 1,
                                         -(INT64_C(1) << (s - 1)), INT64_C(1) << (s - 1)};
                x = edge[n];
            }
#if HAVE_EXACT_REF
            const long double q = ldexpl((long double)x, -(int)s);
            const long double fl = floorl(q);
            const long double want_round = fl + ((q - fl) >= 0.5L ? 1.0L : 0.0L);
            if ((long double)mc_fx_rshift_round_i64(x, s) != want_round
                || (long double)mc_fx_rshift_floor_i64(x, s) != fl) {
                ++bad;
            }
#else
            const int64_t f = mc_fx_rshift_floor_i64(x, s);
            if (mc_fx_rshift_round_i64(x, s) - f > 1 || mc_fx_rshift_round_i64(x, s) < f) {
                ++bad;
            }
#endif
        }
    }
    CHECK_EQ_INT(bad, 0);
}

static void test_errors(void)
{
    const int32_t eye[9] = {T30, 0, 0, 0, T30, 0, 0, 0, T30};
    const int32_t zero3[3] = {0, 0, 0};
    mc_params_t p = make_params(0, 15, eye, zero3);
    mc_correction_t c;
    const int16_t raw[3] = {1, 2, 3};
    int32_t out[3] = {7, 7, 7};

    CHECK_EQ_INT(mc_correction_init(NULL, &p), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_init(&c, NULL), MC_E_ARG);
    CHECK(c.ready != MC_CORRECTION_READY);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);

    memset(&c, 0, sizeof c);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
    CHECK_EQ_INT(mc_correction_apply_n(&c, raw, 1, out), MC_E_STATE);
    CHECK_EQ_INT(out[0], 7);

    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(c.ready, MC_CORRECTION_READY);
    CHECK_EQ_INT(c.shift, 29);
    CHECK_EQ_INT(mc_correction_apply(NULL, raw, out), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply(&c, NULL, out), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply_n(NULL, raw, 1, out), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply_n(&c, NULL, 1, out), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply_n(&c, raw, 1, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_correction_apply_n(&c, raw, 0, out), MC_E_ARG);

    /* every refusal of the validation comes through init, distinct, and leaves c not ready */
    mc_params_t bad;
    bad = p;
    bad.version = 2u;
    CHECK_EQ_INT(mc_correction_init(&c, &bad), MC_E_VERSION);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    bad = p;
    bad.d_inv_exp = 40;
    CHECK_EQ_INT(mc_correction_init(&c, &bad), MC_E_EXPONENT);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    bad = p;
    bad.offset[2] = T30 + 1;
    CHECK_EQ_INT(mc_correction_init(&c, &bad), MC_E_RANGE);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    bad = p;
    bad.d_inv[8] = 0;
    CHECK_EQ_INT(mc_correction_init(&c, &bad), MC_E_SINGULAR);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    bad = p;
    bad.d_inv[8] = T30 / 1000;
    CHECK_EQ_INT(mc_correction_init(&c, &bad), MC_E_CONDITION);
    CHECK_EQ_INT(mc_correction_apply(&c, raw, out), MC_E_STATE);
}

static void test_known_values(void)
{
    mc_correction_t c;
    int32_t out[3];
    /* Unit-scale identity, o = (0.5, -1, 100.25) counts, output in counts with E_m = 15
     * (16 fractional bits): out = (y - o) 2^16 exactly. */
    const int32_t eye[9] = {T30, 0, 0, 0, T30, 0, 0, 0, T30};
    const int32_t o[3] = {16384, -32768, 100 * 32768 + 8192};
    mc_params_t p = make_params(0, 15, eye, o);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    const int16_t y[3] = {-32768, 32767, 100};
    CHECK_EQ_INT(mc_correction_apply(&c, y, out), MC_OK);
    CHECK_EQ_INT(out[0], INT32_MIN); /* -32768.5 2^16 = -2^31 - 2^15: saturates */
    CHECK_EQ_INT(out[1], INT32_MAX); /* 32768 counts = 2^31: saturates */
    CHECK_EQ_INT(out[2], -16384);                            /* -0.25 count */
    /* the same with E_m = 16: no saturation */
    p.out_exp = 16;
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(mc_correction_apply(&c, y, out), MC_OK);
    CHECK_EQ_INT(out[0], -32768 * 32768 - 16384);
    CHECK_EQ_INT(out[1], 32768 * 32768);
    CHECK_EQ_INT(out[2], -8192);

    /* Counts-scale: D^-1 = I / 64 (E_d = -6), unit output with E_m = 10: m = (y - o) / 64 in
     * Q11.21. */
    const int32_t zero3[3] = {0, 0, 0};
    p = make_params(-6, 10, eye, zero3);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    const int16_t y2[3] = {64, -64, 1};
    CHECK_EQ_INT(mc_correction_apply(&c, y2, out), MC_OK);
    CHECK_EQ_INT(out[0], 1 << 21);
    CHECK_EQ_INT(out[1], -(1 << 21));
    CHECK_EQ_INT(out[2], 1 << 15);

    /* Ties round toward +infinity: mantissas 1 (D^-1 = 2^-30 I), shift 1 (E_m = -13), so
     * out = round(diff / 2) with diff = -offset at y = 0. */
    const int32_t tiny_eye[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    const int32_t o_ties[3] = {-1, 1, 3};
    p = make_params(0, -13, tiny_eye, o_ties);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(c.shift, 1);
    const int16_t y0[3] = {0, 0, 0};
    CHECK_EQ_INT(mc_correction_apply(&c, y0, out), MC_OK);
    CHECK_EQ_INT(out[0], 1);  /* 0.5 */
    CHECK_EQ_INT(out[1], 0);  /* -0.5 */
    CHECK_EQ_INT(out[2], -1); /* -1.5 */

    /* A full matrix against hand-computed values: D^-1 = [[1, 0.5, 0], [-0.25, 1, 0], [0, 0,
     * 2]] (E_d = 1), o = 0, E_m = 15 (out = m 2^16). */
    const int32_t full[9] = {T30 / 2, T30 / 4, 0, -T30 / 8, T30 / 2, 0, 0, 0, T30};
    p = make_params(1, 15, full, zero3);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    const int16_t y3[3] = {100, -40, -7};
    CHECK_EQ_INT(mc_correction_apply(&c, y3, out), MC_OK);
    CHECK_EQ_INT(out[0], 80 * 65536);
    CHECK_EQ_INT(out[1], -65 * 65536);
    CHECK_EQ_INT(out[2], -14 * 65536);
}

/* Saturation forced at the extremes: the largest accumulator magnitude (3 2^61, every
 * mantissa and offset at 2^30, inputs at the int16 limits) with the smallest and largest
 * shifts. */
static void test_extremes(void)
{
    /* rows: all -1, (1, -1, 1), (1, 1, -1): det = -4, kappa_inf = 3 */
    const int32_t signs[9] = {-T30, -T30, -T30, T30, -T30, T30, T30, T30, -T30};
    const int32_t o_max[3] = {T30, T30, T30};
    const int32_t o_min[3] = {-T30, -T30, -T30};
    const int16_t y_min[3] = {INT16_MIN, INT16_MIN, INT16_MIN};
    const int16_t y_max[3] = {INT16_MAX, INT16_MAX, INT16_MAX};
    mc_correction_t c;
    int32_t out[3];

    /* shift 0 (E_m = E_d - 14): every non-zero result beyond 2^31 saturates */
    mc_params_t p = make_params(-18, -32, signs, o_max);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(c.shift, 0);
    CHECK_EQ_INT(mc_correction_apply(&c, y_min, out), MC_OK); /* diff = -2^31 each */
    CHECK_EQ_INT(out[0], INT32_MAX);                          /* +3 2^61 */
    CHECK_EQ_INT(out[1], INT32_MIN);                          /* -2^61 */
    CHECK_EQ_INT(out[2], INT32_MIN);
    p = make_params(-18, -32, signs, o_min);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(mc_correction_apply(&c, y_max, out), MC_OK); /* diff = 2^31 - 2^15 */
    CHECK_EQ_INT(out[0], INT32_MIN);
    CHECK_EQ_INT(out[1], INT32_MAX);
    CHECK_EQ_INT(out[2], INT32_MAX);

    /* shift 62 (E_d = -16, E_m = 32): out = round(acc / 2^62) */
    p = make_params(-16, 32, signs, o_max);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(c.shift, 62);
    CHECK_EQ_INT(mc_correction_apply(&c, y_min, out), MC_OK);
    CHECK_EQ_INT(out[0], 2);  /* 3 2^61 / 2^62 = 1.5 -> 2 */
    CHECK_EQ_INT(out[1], 0);  /* -0.5 -> 0 */
    CHECK_EQ_INT(out[2], 0);

    /* shift 30: out = acc / 2^30, 3 2^31 saturates, 2^31 too (one beyond INT32_MAX) */
    p = make_params(0, 16, signs, o_max);
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(mc_correction_apply(&c, y_min, out), MC_OK);
    CHECK_EQ_INT(out[0], INT32_MAX);
    CHECK_EQ_INT(out[1], INT32_MIN); /* -2^31 exactly: representable, not clipped */
    CHECK_EQ_INT(out[2], INT32_MIN);
    /* just inside: the same with shift 31 */
    p.out_exp = 17;
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    CHECK_EQ_INT(mc_correction_apply(&c, y_min, out), MC_OK);
    CHECK_EQ_INT(out[0], INT32_MAX); /* 3 2^30 > INT32_MAX */
    CHECK_EQ_INT(out[1], -(INT32_C(1) << 30));

    /* the saturation is monotone: sweeping y over the whole int16 range, out never wraps */
    const int32_t eye[9] = {T30, 0, 0, 0, T30, 0, 0, 0, T30};
    const int32_t zero3[3] = {0, 0, 0};
    p = make_params(0, 10, eye, zero3); /* +-1024 counts */
    CHECK_EQ_INT(mc_correction_init(&c, &p), MC_OK);
    int32_t prev = INT32_MIN;
    int monotone = 1, sat_lo = 0, sat_hi = 0;
    for (int32_t v = INT16_MIN; v <= INT16_MAX; ++v) {
        const int16_t y[3] = {(int16_t)v, 0, 0};
        mc_correction_apply(&c, y, out);
        monotone &= out[0] >= prev;
        prev = out[0];
        sat_lo += out[0] == INT32_MIN;
        sat_hi += out[0] == INT32_MAX;
    }
    CHECK(monotone);
    CHECK_EQ_INT(sat_lo, 32768 - 1024 + 1); /* y <= -1024 */
    CHECK_EQ_INT(sat_hi, 32767 - 1024 + 1); /* y >= 1024 (1024 2^21 = 2^31) */
}

/* D^-1 as float64 -> mantissas with the smallest E_d that holds the largest entry. */
static int quantise_matrix(const double m[9], int32_t d[9])
{
    double amax = 0.0;
    for (int k = 0; k < 9; ++k) {
        amax = fabs(m[k]) > amax ? fabs(m[k]) : amax;
    }
    int e;
    const double fr = frexp(amax, &e); /* amax = fr 2^e, fr in [0.5, 1) */
    if (fr == 0.5) {
        e -= 1;
    }
    for (int k = 0; k < 9; ++k) {
        d[k] = (int32_t)llround(ldexp(m[k], 30 - e));
    }
    return e;
}

/* Smallest E_m no int16 input saturates (float64 estimate with a margin; the tests only need
 * a plausible default). */
static int fit_out_exp(const mc_params_t *p)
{
    double worst = 0.0;
    for (int i = 0; i < 3; ++i) {
        double row = 0.0;
        for (int j = 0; j < 3; ++j) {
            row += fabs(ldexp((double)p->d_inv[3 * i + j], p->d_inv_exp - 30))
                * (32768.0 + fabs(ldexp((double)p->offset[j], -15)));
        }
        worst = row > worst ? row : worst;
    }
    int e;
    frexp(worst, &e); /* worst < 2^e */
    return e;
}

static void test_random(void)
{
    const int n_sets = 2000, n_per_set = 500;
    long cases = 0, saturated = 0, exact_ok = 0, refused = 0, within_half = 0;
    double max_err = 0.0; /* |out - ref| over unsaturated outputs, LSB */
    double max_err_clipped = 0.0;
    int kinds[4] = {0, 0, 0, 0};
    for (int set = 0; set < n_sets; ++set) {
        mc_params_t p;
        memset(&p, 0, sizeof p);
        p.version = MC_PARAMS_FORMAT_VERSION;
        const int kind = set % 4;
        mc_correction_t c;
        mc_status_t st;
        do {
            double m[9];
            double scale = 1.0;
            if (kind == 0) { /* unit-scale: D^-1 near I, o up to 2000 counts */
                scale = 0.5 + rng_unit();
            } else if (kind == 1) { /* counts-scale: field of 30 to 30000 counts */
                scale = 1.0 / (30.0 * pow(1000.0, rng_unit()));
            } else if (kind == 2) { /* the other way: entries about 60 */
                scale = 60.0 * (0.5 + rng_unit());
            }
            for (int k = 0; k < 9; ++k) {
                m[k] = scale * ((k % 4 == 0 ? 1.0 : 0.0) + 0.3 * (2.0 * rng_unit() - 1.0));
            }
            int32_t o[3];
            for (int j = 0; j < 3; ++j) {
                o[j] = (int32_t)rng_int(-2000 * 32768, 2000 * 32768);
            }
            if (kind == 3) { /* extreme: any mantissa, any offset, any exponent */
                for (int k = 0; k < 9; ++k) {
                    p.d_inv[k] = (int32_t)rng_int(-T30, T30);
                }
                for (int j = 0; j < 3; ++j) {
                    o[j] = (int32_t)rng_int(-T30, T30);
                }
                p.d_inv_exp = (int8_t)rng_int(MC_PARAMS_EXP_MIN, MC_PARAMS_EXP_MAX);
            } else {
                p.d_inv_exp = (int8_t)quantise_matrix(m, p.d_inv);
            }
            memcpy(p.offset, o, sizeof o);
            /* half the sets with the default output exponent, half with any allowed one
             * (down to shift 0: many saturate; up to 62: tiny outputs) */
            const int lo = p.d_inv_exp - 14 > MC_PARAMS_EXP_MIN ? p.d_inv_exp - 14 : MC_PARAMS_EXP_MIN;
            const int hi = p.d_inv_exp + 48 < MC_PARAMS_EXP_MAX ? p.d_inv_exp + 48 : MC_PARAMS_EXP_MAX;
            int e_m = (set / 4) % 2 == 0 ? fit_out_exp(&p) : (int)rng_int(lo, hi);
            e_m = e_m < lo ? lo : e_m > hi ? hi : e_m;
            p.out_exp = (int8_t)e_m;
            st = mc_correction_init(&c, &p);
            refused += st != MC_OK;
        } while (st != MC_OK);
        ++kinds[kind];

        for (int n = 0; n < n_per_set; ++n) {
            int16_t y[3];
            for (int j = 0; j < 3; ++j) {
                const uint64_t r = rng_next() % 16u;
                if (r == 0) {
                    y[j] = INT16_MIN;
                } else if (r == 1) {
                    y[j] = INT16_MAX;
                } else if (r < 8) { /* near the offset, as a real field would be */
                    y[j] = mc_fx_sat_i16(p.offset[j] / 32768 + rng_int(-1000, 1000));
                } else {
                    y[j] = (int16_t)rng_int(INT16_MIN, INT16_MAX);
                }
            }
            int32_t out[3];
            if (mc_correction_apply(&c, y, out) != MC_OK) {
                CHECK(0 && "apply failed");
                return;
            }
            for (int i = 0; i < 3; ++i) {
                ++cases;
                const double ref = ref_lsb(&p, y, i);
                const double err_clipped = fabs((double)out[i] - clip_out(ref));
                max_err_clipped = err_clipped > max_err_clipped ? err_clipped : max_err_clipped;
                const int sat = ref > (double)INT32_MAX + 0.5 || ref < (double)INT32_MIN - 0.5;
                saturated += sat;
                if (!sat) {
                    const double err = fabs((double)out[i] - ref);
                    max_err = err > max_err ? err : max_err;
                    within_half += err <= 0.5 + 0x1.0p-20;
                } else {
                    within_half += out[i] == (ref > 0 ? INT32_MAX : INT32_MIN);
                }
#if HAVE_EXACT_REF
                exact_ok += out[i] == exact_out(&p, y, i);
#else
                exact_ok += 1;
#endif
            }
        }
    }
    printf("  random: %ld outputs (%ld saturated) over %d parameter sets (%d unit-scale, %d "
           "counts-scale, %d entries ~60, %d extreme; %ld refused by validation and redrawn)\n",
           cases, saturated, n_sets, kinds[0], kinds[1], kinds[2], kinds[3], refused);
    printf("  random: max |out - clip(ref)| = %.9f LSB; max |out - ref| unsaturated = %.9f LSB; "
           "bit-exact vs exact reference: %ld/%ld%s\n",
           max_err_clipped, max_err, exact_ok, cases,
           HAVE_EXACT_REF ? "" : " (no exact long double here: skipped)");
    CHECK(cases >= 1000000);
    CHECK(saturated > 1000 && saturated < cases / 2);
    CHECK(max_err_clipped <= 1.0);
    CHECK(max_err <= 0.5 + 0x1.0p-20);
    CHECK_EQ_INT(within_half, cases);
    CHECK_EQ_INT(exact_ok, cases);
}

int main(void)
{
    test_fixed_helpers();
    test_errors();
    test_known_values();
    test_extremes();
    test_random();
    return check_summary("test_fw_correction");
}
