/* SPDX-License-Identifier: Apache-2.0 */
/* The parameter set: every validation refusal with its own status code (and the order of the
 * checks), the exact integer conditioning test against a float64 computation on random
 * matrices, and the byte encoding (golden bytes, round trip, errors). */
#include "check.h"
#include "magcal/params.h"

#include <math.h>
#include <stdint.h>
#include <string.h>

#define T30 (INT32_C(1) << 30)

static mc_params_t identity_params(void)
{
    mc_params_t p;
    memset(&p, 0, sizeof p);
    p.version = MC_PARAMS_FORMAT_VERSION;
    p.d_inv_exp = 0;
    p.out_exp = 15;
    p.d_inv[0] = p.d_inv[4] = p.d_inv[8] = T30;
    return p;
}

static void set_matrix(mc_params_t *p, const int32_t a[9])
{
    memcpy(p->d_inv, a, sizeof p->d_inv);
}

static uint64_t rng_state = 0x9E3779B97F4A7C15u;

/* splitmix64 */
static uint64_t rng_next(void)
{
    uint64_t z = (rng_state += UINT64_C(0x9E3779B97F4A7C15));
    z = (z ^ (z >> 30)) * UINT64_C(0xBF58476D1CE4E5B9);
    z = (z ^ (z >> 27)) * UINT64_C(0x94D049BB133111EB);
    return z ^ (z >> 31);
}

/* uniform in [0, 1) */
static double rng_unit(void)
{
    return (double)(rng_next() >> 11) * 0x1.0p-53;
}

/* kappa_inf of a in double, through the inverse from cofactors (a is well scaled here). */
static double kappa_inf(const int32_t m[9])
{
    double a[9], c[9];
    for (int k = 0; k < 9; ++k) {
        a[k] = (double)m[k];
    }
    c[0] = a[4] * a[8] - a[5] * a[7];
    c[1] = a[5] * a[6] - a[3] * a[8];
    c[2] = a[3] * a[7] - a[4] * a[6];
    c[3] = a[2] * a[7] - a[1] * a[8];
    c[4] = a[0] * a[8] - a[2] * a[6];
    c[5] = a[1] * a[6] - a[0] * a[7];
    c[6] = a[1] * a[5] - a[2] * a[4];
    c[7] = a[2] * a[3] - a[0] * a[5];
    c[8] = a[0] * a[4] - a[1] * a[3];
    const double det = a[0] * c[0] + a[1] * c[1] + a[2] * c[2];
    double na = 0.0, ninv = 0.0;
    for (int i = 0; i < 3; ++i) {
        const double row = fabs(a[3 * i]) + fabs(a[3 * i + 1]) + fabs(a[3 * i + 2]);
        const double col = fabs(c[i]) + fabs(c[3 + i]) + fabs(c[6 + i]);
        na = row > na ? row : na;
        ninv = col > ninv ? col : ninv;
    }
    return na * ninv / fabs(det);
}

static void test_validate_refusals(void)
{
    mc_params_t p = identity_params();
    CHECK_EQ_INT(mc_params_validate(NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);

    /* Version. */
    const uint16_t bad_versions[] = {0u, 2u, 0x0100u, 0xFFFFu};
    for (size_t k = 0; k < sizeof bad_versions / sizeof bad_versions[0]; ++k) {
        p = identity_params();
        p.version = bad_versions[k];
        CHECK_EQ_INT(mc_params_validate(&p), MC_E_VERSION);
    }

    /* Exponents: each bound, and the shift 14 + E_m - E_d in [0, 62]. */
    p = identity_params();
    p.d_inv_exp = MC_PARAMS_EXP_MIN - 1;
    p.out_exp = (int8_t)(p.d_inv_exp - 14);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.d_inv_exp = MC_PARAMS_EXP_MAX + 1;
    p.out_exp = MC_PARAMS_EXP_MAX;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.d_inv_exp = 0;
    p.out_exp = MC_PARAMS_EXP_MAX + 1;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.d_inv_exp = -20;
    p.out_exp = MC_PARAMS_EXP_MIN - 1;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.d_inv_exp = -128;
    p.out_exp = 127;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    /* shift = -1 refused, 0 accepted */
    p.d_inv_exp = 5;
    p.out_exp = 5 - 15;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.out_exp = 5 - 14;
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
    /* shift = 62 accepted, 63 refused */
    p.d_inv_exp = -16;
    p.out_exp = 32;
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
    p.d_inv_exp = -17;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    /* every exponent of the range with a shift in range */
    for (int e = MC_PARAMS_EXP_MIN; e <= MC_PARAMS_EXP_MAX; ++e) {
        p.d_inv_exp = (int8_t)e;
        p.out_exp = (int8_t)(e + 20 <= MC_PARAMS_EXP_MAX ? e + 20 : e);
        CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
    }

    /* Range: each entry just beyond +-2^30 (and at the int32 limits); +-2^30 itself is fine. */
    const int32_t bad_values[] = {T30 + 1, -T30 - 1, INT32_MAX, INT32_MIN};
    for (int k = 0; k < 9; ++k) {
        for (size_t v = 0; v < 4; ++v) {
            p = identity_params();
            p.d_inv[k] = bad_values[v];
            CHECK_EQ_INT(mc_params_validate(&p), MC_E_RANGE);
        }
    }
    for (int j = 0; j < 3; ++j) {
        for (size_t v = 0; v < 4; ++v) {
            p = identity_params();
            p.offset[j] = bad_values[v];
            CHECK_EQ_INT(mc_params_validate(&p), MC_E_RANGE);
        }
        p = identity_params();
        p.offset[j] = T30;
        CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
        p.offset[j] = -T30;
        CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
    }
    p = identity_params();
    p.d_inv[0] = p.d_inv[4] = -T30;
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);

    /* Singular, exactly: zero matrix, a zero row, dependent rows with full-size entries (a
     * float determinant of these would not be exactly 0 in general). */
    const int32_t zero[9] = {0};
    p = identity_params();
    set_matrix(&p, zero);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_SINGULAR);
    const int32_t zero_row[9] = {T30, 5, 7, 0, 0, 0, 3, 9, T30};
    set_matrix(&p, zero_row);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_SINGULAR);
    /* row 2 = row 0 + row 1 */
    const int32_t dependent[9] = {536870911, -123456789, 987654321, 536870913, 123456789,
                                  -987654321 + 55, T30, 0, 55};
    set_matrix(&p, dependent);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_SINGULAR);
    /* column 2 = column 0 + column 1 */
    const int32_t dep_cols[9] = {600000007, 12345, 600012352, -500000000, 400000001,
                                 -99999999, 333333333, -700000007, -366666674};
    set_matrix(&p, dep_cols);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_SINGULAR);
    /* Row 2 = row 0 + row 1 + (0, 0, 1): nearly singular (kappa about 1e9), not singular. */
    const int32_t nearly[9] = {536870911, -123456789, 987654321, 536870913, 123456789,
                               -987654321 + 55, T30, 0, 56};
    set_matrix(&p, nearly);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_CONDITION);

    /* Condition boundary: kappa_inf(diag(100 k, 100 k, k)) = 100 exactly is accepted; one
     * mantissa step more is refused (MC_PARAMS_COND_MAX = 100 by default). */
    const int32_t k20 = INT32_C(1) << 20;
    const int32_t at_bound[9] = {100 * k20, 0, 0, 0, -100 * k20, 0, 0, 0, k20};
    set_matrix(&p, at_bound);
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);
    const int32_t past_bound[9] = {100 * k20 + 1, 0, 0, 0, 100 * k20, 0, 0, 0, k20};
    set_matrix(&p, past_bound);
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_CONDITION);
    const int32_t also_at_bound[9] = {100 * k20 - 1, 0, 0, 0, 100 * k20, 0, 0, 0, -k20};
    set_matrix(&p, also_at_bound);
    CHECK_EQ_INT(mc_params_validate(&p), MC_OK);

    /* Order of the checks: version before exponent before range before the matrix. */
    p = identity_params();
    set_matrix(&p, zero);
    p.offset[0] = INT32_MIN;
    p.out_exp = 100;
    p.version = 7u;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_VERSION);
    p.version = MC_PARAMS_FORMAT_VERSION;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_EXPONENT);
    p.out_exp = 15;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_RANGE);
    p.offset[0] = 0;
    CHECK_EQ_INT(mc_params_validate(&p), MC_E_SINGULAR);
}

/* The exact integer test agrees with kappa_inf computed in double on random matrices whose
 * conditioning spans 1 to 1e5, except within 1e-9 of the bound (none expected). */
static void test_condition_random(void)
{
    int agree = 0, near = 0, refused = 0, accepted = 0;
    mc_params_t p = identity_params();
    for (int n = 0; n < 100000; ++n) {
        double a[9], amax = 0.0;
        const double squash = pow(10.0, -5.0 * rng_unit()); /* shrinks one column */
        const int col = (int)(rng_next() % 3u);
        for (int k = 0; k < 9; ++k) {
            a[k] = 2.0 * rng_unit() - 1.0;
            if (k % 3 == col) {
                a[k] *= squash;
            }
            amax = fabs(a[k]) > amax ? fabs(a[k]) : amax;
        }
        /* mantissas with the largest entry at 2^30, or smaller ones (2^10 to 2^30) */
        const double scale = ldexp(1.0, 10 + (int)(rng_next() % 21u)) / amax;
        for (int k = 0; k < 9; ++k) {
            p.d_inv[k] = (int32_t)lround(a[k] * scale);
        }
        const mc_status_t st = mc_params_validate(&p);
        const double kappa = kappa_inf(p.d_inv);
        if (!(kappa < 1e12)) {
            continue; /* singular or hopeless in double: not a useful comparison */
        }
        if (fabs(kappa - (double)MC_PARAMS_COND_MAX) < 1e-9 * (double)MC_PARAMS_COND_MAX) {
            ++near;
            continue;
        }
        const mc_status_t want = kappa <= (double)MC_PARAMS_COND_MAX ? MC_OK : MC_E_CONDITION;
        if (st == want) {
            ++agree;
        } else {
            printf("  kappa %.17g: got %d want %d\n", kappa, (int)st, (int)want);
        }
        refused += st == MC_E_CONDITION;
        accepted += st == MC_OK;
    }
    printf("  conditioning: %d random matrices agree with float64 (%d accepted, %d refused, %d "
           "within 1e-9 of the bound)\n",
           agree, accepted, refused, near);
    CHECK(agree > 90000);
    CHECK(accepted > 10000 && refused > 10000);
    CHECK_EQ_INT(agree, accepted + refused);
}

static void test_encoding(void)
{
    mc_params_t p;
    memset(&p, 0, sizeof p);
    p.version = MC_PARAMS_FORMAT_VERSION;
    p.d_inv_exp = -5;
    p.out_exp = 9;
    for (int k = 0; k < 9; ++k) {
        p.d_inv[k] = (int32_t)(0x01020304 * (k + 1)) * (k % 2 ? -1 : 1);
    }
    p.offset[0] = -1;
    p.offset[1] = T30;
    p.offset[2] = INT32_MIN;

    uint8_t buf[MC_PARAMS_ENCODED_SIZE + 8];
    size_t written = 99u;
    memset(buf, 0xAA, sizeof buf);
    CHECK_EQ_INT(mc_params_encode(&p, buf, sizeof buf, &written), MC_OK);
    CHECK_EQ_INT(written, MC_PARAMS_ENCODED_SIZE);
    CHECK_EQ_INT(buf[MC_PARAMS_ENCODED_SIZE], 0xAA); /* nothing beyond the encoding */
    /* golden bytes of the header and of a few fields */
    CHECK_EQ_INT(buf[0], 0x01);
    CHECK_EQ_INT(buf[1], 0x00);
    CHECK_EQ_INT(buf[2], 0xFB); /* -5 */
    CHECK_EQ_INT(buf[3], 0x09);
    CHECK_EQ_INT(buf[4], 0x04); /* d_inv[0] = 0x01020304, little-endian */
    CHECK_EQ_INT(buf[5], 0x03);
    CHECK_EQ_INT(buf[6], 0x02);
    CHECK_EQ_INT(buf[7], 0x01);
    CHECK_EQ_INT(buf[8], 0xF8); /* d_inv[1] = -0x02040608 = 0xFDFBF9F8 */
    CHECK_EQ_INT(buf[9], 0xF9);
    CHECK_EQ_INT(buf[10], 0xFB);
    CHECK_EQ_INT(buf[11], 0xFD);
    const uint8_t tail[12] = {0xFF, 0xFF, 0xFF, 0xFF, 0x00, 0x00, 0x00, 0x40,
                              0x00, 0x00, 0x00, 0x80};
    CHECK(memcmp(buf + 40, tail, sizeof tail) == 0);

    mc_params_t q;
    memset(&q, 0x55, sizeof q);
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE, &q), MC_OK);
    CHECK_EQ_INT(q.version, p.version);
    CHECK_EQ_INT(q.d_inv_exp, -5);
    CHECK_EQ_INT(q.out_exp, 9);
    CHECK(memcmp(q.d_inv, p.d_inv, sizeof p.d_inv) == 0);
    CHECK(memcmp(q.offset, p.offset, sizeof p.offset) == 0);

    /* round trip of random sets, including out-of-range values (decode does not validate) */
    for (int n = 0; n < 10000; ++n) {
        mc_params_t r, s;
        r.version = MC_PARAMS_FORMAT_VERSION;
        r.d_inv_exp = (int8_t)((int)(rng_next() % 256u) - 128);
        r.out_exp = (int8_t)((int)(rng_next() % 256u) - 128);
        for (int k = 0; k < 9; ++k) {
            r.d_inv[k] = (int32_t)((int64_t)(rng_next() % UINT64_C(0x100000000)) - INT64_C(0x80000000));
        }
        for (int j = 0; j < 3; ++j) {
            r.offset[j] = (int32_t)((int64_t)(rng_next() % UINT64_C(0x100000000)) - INT64_C(0x80000000));
        }
        uint8_t b[MC_PARAMS_ENCODED_SIZE];
        size_t w = 0u;
        if (mc_params_encode(&r, b, sizeof b, &w) != MC_OK || w != sizeof b
            || mc_params_decode(b, w, &s) != MC_OK || s.version != r.version
            || s.d_inv_exp != r.d_inv_exp || s.out_exp != r.out_exp
            || memcmp(s.d_inv, r.d_inv, sizeof r.d_inv) != 0
            || memcmp(s.offset, r.offset, sizeof r.offset) != 0) {
            CHECK(0 && "random round trip");
            break;
        }
    }

    /* errors */
    CHECK_EQ_INT(mc_params_encode(NULL, buf, sizeof buf, &written), MC_E_ARG);
    CHECK_EQ_INT(mc_params_encode(&p, NULL, sizeof buf, &written), MC_E_ARG);
    CHECK_EQ_INT(mc_params_encode(&p, buf, sizeof buf, NULL), MC_E_ARG);
    written = 7u;
    CHECK_EQ_INT(mc_params_encode(&p, buf, MC_PARAMS_ENCODED_SIZE - 1, &written), MC_E_NO_SPACE);
    CHECK_EQ_INT(written, 0);
    CHECK_EQ_INT(mc_params_encode(&p, buf, 0, &written), MC_E_NO_SPACE);

    CHECK_EQ_INT(mc_params_encode(&p, buf, sizeof buf, &written), MC_OK);
    memset(&q, 0x55, sizeof q);
    const mc_params_t untouched = q;
    CHECK_EQ_INT(mc_params_decode(NULL, MC_PARAMS_ENCODED_SIZE, &q), MC_E_ARG);
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_params_decode(buf, 0, &q), MC_E_LENGTH);
    CHECK_EQ_INT(mc_params_decode(buf, 1, &q), MC_E_LENGTH);
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE - 1, &q), MC_E_LENGTH);
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE + 1, &q), MC_E_LENGTH);
    buf[0] = 2u;
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE, &q), MC_E_VERSION);
    CHECK_EQ_INT(mc_params_decode(buf, 2, &q), MC_E_VERSION);
    buf[0] = 1u;
    buf[1] = 1u; /* version 0x0101 */
    CHECK_EQ_INT(mc_params_decode(buf, MC_PARAMS_ENCODED_SIZE, &q), MC_E_VERSION);
    CHECK(memcmp(&q, &untouched, sizeof q) == 0); /* *p written only on MC_OK */
}

int main(void)
{
    test_validate_refusals();
    test_condition_random();
    test_encoding();
    return check_summary("test_fw_params");
}
