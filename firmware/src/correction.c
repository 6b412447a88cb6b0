/* SPDX-License-Identifier: Apache-2.0 */
/* The fixed-point correction m = D^-1 (y - o). See correction.h. */
#include "magcal/correction.h"

#include "magcal/fixed.h"

mc_status_t mc_correction_init(mc_correction_t *c, const mc_params_t *p)
{
    if (c == NULL) {
        return MC_E_ARG;
    }
    c->ready = 0u;
    if (p == NULL) {
        return MC_E_ARG;
    }
    const mc_status_t st = mc_params_validate(p);
    if (st != MC_OK) {
        return st;
    }
    c->params = *p;
    c->shift = (uint8_t)(14 + p->out_exp - p->d_inv_exp); /* in [0, 62]: validated */
    c->ready = MC_CORRECTION_READY;
    return MC_OK;
}

mc_status_t mc_correction_apply(const mc_correction_t *c, const int16_t raw[3], int32_t out[3])
{
    if (c == NULL || raw == NULL || out == NULL) {
        return MC_E_ARG;
    }
    if (c->ready != MC_CORRECTION_READY) {
        return MC_E_STATE;
    }
    /* Scaling and overflow: see correction.h. The kernel lives here, not in a helper, so that
     * this symbol's disassembly is the whole per-sample cost. */
    const int32_t *d = c->params.d_inv;
    const int32_t *o = c->params.offset;
    /* y 2^15 as a product (|.| <= 2^30), not a shift, which would be undefined for y < 0. */
    const int32_t diff0 = (int32_t)raw[0] * 32768 - o[0];
    const int32_t diff1 = (int32_t)raw[1] * 32768 - o[1];
    const int32_t diff2 = (int32_t)raw[2] * 32768 - o[2];
    const unsigned s = c->shift;
    for (int i = 0; i < 3; ++i) {
        const int64_t acc = (int64_t)d[3 * i] * diff0 + (int64_t)d[3 * i + 1] * diff1
            + (int64_t)d[3 * i + 2] * diff2;
        out[i] = mc_fx_sat_i32(mc_fx_rshift_round_i64(acc, s));
    }
    return MC_OK;
}

mc_status_t mc_correction_apply_n(const mc_correction_t *c, const int16_t *raw, size_t n,
                                  int32_t *out)
{
    if (c == NULL || raw == NULL || out == NULL || n == 0u) {
        return MC_E_ARG;
    }
    if (c->ready != MC_CORRECTION_READY) {
        return MC_E_STATE;
    }
    for (size_t k = 0; k < n; ++k) {
        (void)mc_correction_apply(c, raw + 3 * k, out + 3 * k); /* cannot fail: checked above */
    }
    return MC_OK;
}
