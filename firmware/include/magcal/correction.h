/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The magnetometer correction m = D^-1 (y - o) in fixed point (docs/contracts.md), with the
 * parameter set of params.h. Integer arithmetic only: no floating point, no division, no
 * library call (on a Cortex-M4 it is 32x32->64 multiply-accumulates, 64-bit adds and
 * shifts).
 *
 * Formats:
 *   raw[i]   int16 raw counts y.
 *   out[i]   int32 m[i] = out[i] * 2^(E_m - 31), E_m = params.out_exp: a signed value in
 *            [-2^E_m, 2^E_m) with 31 - E_m fractional bits. The exponent is per parameter set
 *            so that both kinds of calibration keep their resolution: a counts-scale D^-1
 *            (unit-norm output; for a field of 500 counts, D^-1 = I/500 with a zero offset has
 *            E_d = -8 and the default E_m = 7 holds any int16 input with a step of 2^-24 of
 *            the field) and a unit-scale one (output in counts; D^-1 = 1.1 I with a zero
 *            offset has E_d = 1, E_m = 16, a step of 2^-15 count). The host chooses E_m
 *            (host/src/magcal/device/fixed_point.py, default_out_exp); by default the smallest
 *            for which (a) no int16 input can saturate and (b) quantising D^-1 and o moves no
 *            output by more than half an LSB for any int16 input (an exact worst case over
 *            the corners of the input range, from the actual quantisation errors). With the
 *            1/2 LSB of the rounding below, the output is then within 1 LSB of the float
 *            correction with the unquantised D^-1 and o. (b) usually costs 1 to 3 exponent
 *            steps over (a) alone (with the offset (123.4, -2000.7, 300.1) counts the I/500
 *            example above gets E_m = 8, a step of 2^-23 of the field); a set whose E_m is
 *            smaller than the default has no such guarantee.
 *
 * Arithmetic, per axis i:
 *   diff[j] = y[j] 2^15 - offset[j]                 int32, exact (Q16.15, |.| <= 2^31)
 *   acc     = sum_j d_inv[3 i + j] diff[j]           int64, exact (45 - E_d fractional bits)
 *   out[i]  = sat32(round(acc / 2^s)),  s = 14 + E_m - E_d  (0 <= s <= 62)
 * acc is the exact value of D^-1 (y - o) for the stored (quantised) parameters, so out[i] is
 * that exact value rounded once to the output format: round to nearest, ties toward +infinity,
 * then saturated. Hence, when not saturated, |out[i] - exact| <= 1/2 LSB; the tests assert
 * <= 1 LSB against a float64 reference and bit equality against an exact emulation, and, for
 * sets with the default E_m, <= 1 LSB against the float correction with the unquantised
 * calibration.
 */
#ifndef MAGCAL_CORRECTION_H
#define MAGCAL_CORRECTION_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/params.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* mc_correction_t.ready after a successful mc_correction_init. */
#define MC_CORRECTION_READY 0x4D43434Fu

/* The saturation limits of an output component. */
#define MC_CORRECTION_OUT_MAX INT32_MAX
#define MC_CORRECTION_OUT_MIN INT32_MIN

/* A correction instance. The caller owns it; the fields are read-only outside correction.c
 * (params.out_exp gives the output format). */
typedef struct {
    mc_params_t params; /* the validated parameter set, copied */
    uint32_t ready;     /* MC_CORRECTION_READY once initialised, 0 otherwise */
    uint8_t shift;      /* s = 14 + E_m - E_d, in [0, 62] */
} mc_correction_t;

/*
 * Validates p (mc_params_validate: MC_E_VERSION, MC_E_EXPONENT, MC_E_RANGE, MC_E_SINGULAR or
 * MC_E_CONDITION on refusal) and prepares c. MC_E_ARG for a NULL pointer. On any error c is
 * left not ready (mc_correction_apply refuses it with MC_E_STATE) unless c is NULL. Call once
 * per parameter write, not per sample.
 */
mc_status_t mc_correction_init(mc_correction_t *c, const mc_params_t *p);

/*
 * out = D^-1 (raw - o) in the output format above. MC_E_ARG for a NULL pointer, MC_E_STATE
 * when c is not initialised; otherwise MC_OK (a saturated output is still MC_OK).
 *
 * Scaling and overflow: diff[j] lies in [-2^31, 2^31 - 2^15] because |raw| <= 2^15 and
 * |offset| <= 2^30 (validated), so it is exact in int32; each product |d_inv| |diff| <=
 * 2^30 2^31 = 2^61 and the sum of three is < 2^63: acc never overflows int64. The rounding
 * shift is exact for every int64 (fixed.h). A result outside [INT32_MIN, INT32_MAX] saturates
 * to MC_CORRECTION_OUT_MIN / MC_CORRECTION_OUT_MAX, never wraps; it can only happen when the
 * parameter set's E_m is smaller than the default choice, so an output equal to one of these
 * limits means "at least this value".
 */
mc_status_t mc_correction_apply(const mc_correction_t *c, const int16_t raw[3], int32_t out[3]);

/*
 * Convenience for batches (and for the ctypes tests): n samples, raw[3 k + i] -> out[3 k + i],
 * each exactly as mc_correction_apply. MC_E_ARG for a NULL pointer or n == 0, MC_E_STATE when
 * c is not initialised. Scaling and overflow: as mc_correction_apply.
 */
mc_status_t mc_correction_apply_n(const mc_correction_t *c, const int16_t *raw, size_t n,
                                  int32_t *out);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_CORRECTION_H */
