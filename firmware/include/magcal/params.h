/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The calibration parameter set the device stores and corrects with, its validation and its
 * fixed little-endian byte encoding (the blob the storage module keeps and the protocol
 * carries; host/src/magcal/device/fixed_point.py writes and reads the same bytes).
 *
 * The correction is m = D^-1 (y - o) (docs/contracts.md), y the raw magnetometer counts.
 *
 * Stored quantities and their fixed-point formats (format version 1):
 *
 *   d_inv[9]     D^-1, row-major, int32 mantissas with 30 fractional bits (Q1.30) scaled by
 *                the set's exponent E_d = d_inv_exp:
 *                    D^-1[i][j] = d_inv[3 i + j] * 2^(E_d - 30),  |d_inv[k]| <= 2^30,
 *                so every entry lies in [-2^E_d, 2^E_d]. The host picks the smallest E_d that
 *                holds the largest entry, which leaves 30 significant bits to that entry
 *                whatever its size: a unit-scale D^-1 (entries about 1, E_d = 0 or 1) and a
 *                counts-scale one (entries about 1/60, E_d = -5, or about 60, E_d = 6) are
 *                quantised equally finely (relative step <= 2^-30).
 *   offset[3]    o in raw counts, int32 with 15 fractional bits (Q16.15):
 *                    o[j] = offset[j] * 2^-15,  |offset[j]| <= 2^30 (|o| <= 32768 counts),
 *                a step of 3.05e-5 count. The bound makes y - o fit an int32 in Q.15.
 *   out_exp      E_m, the exponent of the correction's output (correction.h):
 *                    m[i] = out[i] * 2^(E_m - 31),
 *                an int32 covering [-2^E_m, 2^E_m) with 31 - E_m fractional bits. The host
 *                picks, by default, the smallest E_m for which no int16 input saturates and
 *                the quantisation of d_inv and offset moves no output by more than half an
 *                LSB (correction.h), so that the output is within 1 LSB of the float
 *                correction with the unquantised calibration.
 *   version      MC_PARAMS_FORMAT_VERSION.
 *
 * Both exponents lie in [MC_PARAMS_EXP_MIN, MC_PARAMS_EXP_MAX], and the correction's shift
 * s = 14 + E_m - E_d (the fractional bits of the exact product minus those of the output) in
 * [0, MC_PARAMS_SHIFT_MAX]: the output is never finer than the exact result.
 *
 * Validation (mc_params_validate) runs once per parameter write, never per sample, in
 * INTEGER arithmetic only: exact 128-bit products built from 32-bit limbs, no floating point
 * and no division, so its verdict is exact and the same on every target and in the host's
 * Python mirror (fixed_point.py uses exact Python integers for the same test). It refuses, in
 * this order, each with its own code:
 *
 *   MC_E_VERSION    version != MC_PARAMS_FORMAT_VERSION;
 *   MC_E_EXPONENT   E_d or E_m outside [MC_PARAMS_EXP_MIN, MC_PARAMS_EXP_MAX], or the shift
 *                   s = 14 + E_m - E_d outside [0, MC_PARAMS_SHIFT_MAX];
 *   MC_E_RANGE      some |d_inv[k]| > 2^30 or |offset[j]| > 2^30;
 *   MC_E_SINGULAR   det(D^-1) == 0 exactly (computed exactly on the mantissas);
 *   MC_E_CONDITION  kappa_inf(D^-1) = ||D^-1||_inf ||D||_inf > MC_PARAMS_COND_MAX (config.h),
 *                   tested exactly as ||A||_inf ||adj A||_inf <= MC_PARAMS_COND_MAX |det A|
 *                   on the mantissa matrix A (the exponent cancels in kappa).
 */
#ifndef MAGCAL_PARAMS_H
#define MAGCAL_PARAMS_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/config.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Format version of mc_params_t and of its encoding. */
#define MC_PARAMS_FORMAT_VERSION 1u

/* Size of the encoding in bytes:
 *   offset 0  uint16 version
 *   offset 2  int8   d_inv_exp (E_d)
 *   offset 3  int8   out_exp (E_m)
 *   offset 4  int32  d_inv[9], row-major
 *   offset 40 int32  offset[3]
 * every field little-endian, two's complement, no padding. */
#define MC_PARAMS_ENCODED_SIZE 52u

/* Fractional bits of the D^-1 mantissas and of the offset. */
#define MC_PARAMS_D_INV_FRAC_BITS 30
#define MC_PARAMS_OFFSET_FRAC_BITS 15
/* Largest allowed |d_inv[k]| and |offset[j]|: 2^30. */
#define MC_PARAMS_D_INV_MAX_ABS (INT32_C(1) << 30)
#define MC_PARAMS_OFFSET_MAX_ABS (INT32_C(1) << 30)
/* Allowed exponents E_d and E_m, and the largest shift 14 + E_m - E_d. */
#define MC_PARAMS_EXP_MIN (-32)
#define MC_PARAMS_EXP_MAX 32
#define MC_PARAMS_SHIFT_MAX 62

typedef struct {
    uint16_t version;    /* MC_PARAMS_FORMAT_VERSION */
    int8_t d_inv_exp;    /* E_d: D^-1[i][j] = d_inv[3 i + j] * 2^(E_d - 30) */
    int8_t out_exp;      /* E_m: corrected m[i] = out[i] * 2^(E_m - 31) */
    int32_t d_inv[9];    /* D^-1 mantissas, row-major, Q1.30 (|.| <= 2^30) */
    int32_t offset[3];   /* o, raw counts in Q16.15 (|.| <= 2^30) */
} mc_params_t;

/*
 * Checks p as described above (MC_OK, or the first refusal's code). MC_E_ARG when p is
 * NULL. Integer arithmetic only (a few hundred operations, no division, no floating point);
 * call it once per parameter write.
 *
 * Scaling and overflow: it returns a verdict, not a scaled value, and its verdict is exact for
 * every mc_params_t, because no intermediate can wrap or saturate. The checks run in the
 * order above, so the conditioning test only ever sees mantissas with |a[k]| <= 2^30 (the
 * range check refuses larger ones, INT32_MIN included, before anything is negated or
 * multiplied). Then: products of two entries are <= 2^60 and each 2x2 cofactor (a difference
 * of two) <= 2^61, exact in int64_t; a row sum of |a| (||A||_inf) is < 2^32 and a column sum
 * of three |cofactors| (||adj A||_inf) < 2^63, exact in uint64_t; det A is summed from terms
 * <= 2^91 as 128-bit magnitudes built from 32-bit limbs (positive and negative terms apart,
 * each sum < 2^93); ||A|| ||adj A|| < 2^95 and MC_PARAMS_COND_MAX |det A| < 2^113 (the bound
 * is at most 10^6 < 2^20, config.h) are exact 128-bit products. Exponents are compared as
 * int, and 14 + E_m - E_d is formed from int8_t values, far from int's limits. The native
 * test (test_fw_params.c) drives the mantissas and offsets to the int32 limits, the exponents
 * past their bounds, and random matrices with entries up to 2^30 against a float reference.
 */
mc_status_t mc_params_validate(const mc_params_t *p);

/* Writes the MC_PARAMS_ENCODED_SIZE bytes of p's encoding to buf[0..len) and sets *written.
 * Does not validate p (mc_params_validate does). MC_E_ARG for a NULL pointer, MC_E_NO_SPACE
 * when len < MC_PARAMS_ENCODED_SIZE (nothing written, *written = 0). */
mc_status_t mc_params_encode(const mc_params_t *p, uint8_t *buf, size_t len, size_t *written);

/* Reads an encoding from buf[0..len) into *p. MC_E_ARG for a NULL pointer; MC_E_VERSION when
 * len >= 2 and the version field is not MC_PARAMS_FORMAT_VERSION (a future version may have
 * another size); otherwise MC_E_LENGTH when len != MC_PARAMS_ENCODED_SIZE. *p is written only
 * on MC_OK. Does not validate the values (mc_params_validate does). */
mc_status_t mc_params_decode(const uint8_t *buf, size_t len, mc_params_t *p);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_PARAMS_H */
